"""The control cycle and the procedures it drives (daemon.service.procedure): the cycle
reaches one only through CycleProcedure, and pretension's run is one."""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

from daemon.service import service
from daemon.service.pretension_run import PretensionRun
from daemon.service.procedure import CycleProcedure


def _uses_of_procedure(source: str) -> set[str]:
    """The attributes `source` reads of anything named `procedure` (a local or
    self.procedure)."""
    used = set()
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Attribute):
            continue
        owner = node.value
        named = (isinstance(owner, ast.Name) and owner.id == "procedure") or (
            isinstance(owner, ast.Attribute) and owner.attr == "procedure"
        )
        if named:
            used.add(node.attr)
    return used


def test_the_cycle_reaches_a_procedure_only_through_its_protocol() -> None:
    """Every member service.py uses of its procedure is CycleProcedure's, every member of
    the protocol is used (none dead), and PretensionRun has each with the protocol's
    signature (a property where the protocol has one)."""
    members = {name for name in vars(CycleProcedure) if not name.startswith("_")}
    assert members == {"winding", "cycle", "before_step", "after_commands", "end"}
    assert _uses_of_procedure(Path(service.__file__).read_text()) == members
    for name in members:
        declared, implemented = getattr(CycleProcedure, name), getattr(PretensionRun, name)
        if isinstance(declared, property):
            assert isinstance(implemented, property), name
        else:
            assert inspect.signature(implemented) == inspect.signature(declared), name


def test_a_use_beyond_the_protocol_is_seen() -> None:
    """The check above finds a member the protocol does not have, on a local or on
    self.procedure."""
    assert _uses_of_procedure("procedure.pretension.phase\nself.procedure.name") == {
        "pretension",
        "name",
    }
