"""A config fuzzer: mutated example configs through check-config's own entry point.

Its own generator (seeded, so every run tries the same cases) mutates the example
configs, the hardware template and a robot file: values swapped for other types (bool,
string, list, mapping, null, large and tiny numbers, NaN, infinities, negative, zero),
keys deleted and unknown keys added, values nested deeply, YAML 1.1 scalars (base-60
numbers, yes/no/on/off, dates, 1_000) and tags written raw, lines duplicated, bytes that
are not UTF-8 text.  Every case must end with exit code 0, or 1 and lines
`error: FILE: ...`, never an exception; and an accepted config must hold every value
the case wrote exactly as written (same type and value; an integer where a float is
expected is the one conversion allowed).  A few cases also run as `python -m daemon.cli
check-config` processes (tests/daemon/test_cli.py runs `run` on the hostile configs it names).
"""

from __future__ import annotations

import contextlib
import copy
import enum
import io
import math
import random
import re
import subprocess
import sys
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import yaml
from pydantic import BaseModel

from cdpr import Robot
from cdpr.description import load_yaml
from cdpr.strict_yaml import MAX_DEPTH
from daemon.cli import check_config
from daemon.cli.run_cmd import load_checked
from daemon.cli.simulated import sim_section

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config"
ROBOT_FILE = CONFIG / "robots" / "reference8.yaml"
CASES = 400
REJECT = object()  # a value the loader must refuse outright

# values written in place of another (each is the value as written: the dumper below
# writes it so that any YAML reader reads it back the same)
HOSTILE: list[Any] = [
    True, False, None, "", "text", "500", "1e3", "yes", "off", "8:20", "0x10", "\ud800",
    "x" * 5000, "/dev/zero", "/", [], [1, 2, 3], ["a"], [None], {}, {"bogus": 1},
    0, -1, 1, 3, 2**62, -(2**62), 0.0, -0.0, 0.5, -2.5, 1e300, -1e300, 1e-300,
    math.nan, math.inf, -math.inf,
]  # fmt: skip
# scalars written raw into the YAML text, with what a YAML 1.2 core reader makes of them
RAW: list[tuple[str, Any]] = [
    ("8:20", "8:20"), ("1:00:00", "1:00:00"), ("yes", "yes"), ("No", "No"), ("on", "on"),
    ("off", "off"), ("y", "y"), ("TRUE", True), ("False", False), ("~", None),
    ("NULL", None), ("0x1F4", 500), ("0o17", 15), ("017", 17), ("+12", 12), ("-0", 0),
    ("0b101", "0b101"), ("1_000", "1_000"), ("5e2", 500.0), (".5", 0.5), ("1.", 1.0),
    ("-.inf", -math.inf), (".NaN", math.nan), ("2001-12-14", "2001-12-14"),
    ("12:30:00", "12:30:00"), ("!!str 12", "12"), ("!!float 3", 3.0), ("&anchor 7", 7),
    ("'quoted'", "quoted"), ("9223372036854775807", 2**63 - 1),
    ("9223372036854775808", REJECT), ("9" * 5000, REJECT), ("-" + "1" * 30, REJECT),
    ("1e400", REJECT), ("!!int 1.5", REJECT), ("!!bool yes", REJECT),
    ("!!binary aGVsbG8=", REJECT), ("!!timestamp 2001-12-14", REJECT), ("!!set {a}", REJECT),
    ("!!python/name:os.system", REJECT), ("!custom 5", REJECT), ("*undefined", REJECT),
]  # fmt: skip
NOT_TEXT = [b"\xff", b"\xfe\xfe", b"\xc3\x28", b"\x80", b"\xed\xa0\x80", b"\x00", b"\x1b"]
DEPTHS = [3, 30, 63, 70, 300, 5000]  # nesting written raw as [[[...]]]


class _Dumper(yaml.SafeDumper):
    """Every string double-quoted: read back as the same string by any YAML reader."""


_Dumper.add_representer(
    str, lambda dumper, value: dumper.represent_scalar("tag:yaml.org,2002:str", value, style='"')
)


def dump(data: Any) -> str:
    return yaml.dump(data, Dumper=_Dumper, sort_keys=False, allow_unicode=False, width=1 << 20)


def _bases() -> dict[str, Any]:
    """The documents mutated: daemon configs (robot inline, or a file path) and a robot."""
    robot = yaml.safe_load(ROBOT_FILE.read_text())
    cia402 = yaml.safe_load((CONFIG / "reference8-cia402.yaml").read_text())
    cia402["robot"] = robot
    cia402["sim"]["plant"]["mismatch"] = {"mass_scale": 1.1, "anchor_error_std": 0.001}
    cia402["sim"]["frame_faults"] = {"seed": 3, "drop": [{"probability": 0.01}]}
    odrive = yaml.safe_load((CONFIG / "reference8-odrive.yaml").read_text())
    odrive["robot"] = str(ROBOT_FILE)
    template = yaml.safe_load((CONFIG / "hardware-template.yaml").read_text())
    template["robot"] = str(ROBOT_FILE)
    template["drives"]["profile"]["eds"] = str(CONFIG / "can" / "cia402_cst.eds")  # not /etc
    suspended = yaml.safe_load((CONFIG / "robots" / "suspended6.yaml").read_text())
    return {"cia402": cia402, "odrive": odrive, "template": template, "robot": suspended}


BASES = _bases()


@dataclass
class Case:
    """One mutated file: its bytes, the values it writes (key path -> value as written,
    or REJECT: the loader must refuse it), and what was done to which base."""

    name: str
    base: str
    text: bytes
    written: dict[tuple[Any, ...], Any] = field(default_factory=dict)
    must_reject: bool = False
    data: Any = None  # the document when the text is its plain dump (a round-trip check)


def _paths(node: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every key path below `node` (containers and leaves)."""
    out = []
    items = node.items() if isinstance(node, dict) else enumerate(node)
    for key, value in items:
        out.append((*prefix, key))
        if isinstance(value, dict | list):
            out += _paths(value, (*prefix, key))
    return out


def _parent(data: Any, path: tuple[Any, ...]) -> Any:
    for part in path[:-1]:
        data = data[part]
    return data


def _dotted(path: tuple[Any, ...]) -> str:
    return ".".join(map(str, path))


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) < 40 else text[:36] + "..."


def _other_value(value: Any, rng: random.Random) -> Any:
    """A value of another kind, or for a number one near its range's edges."""
    if isinstance(value, int | float) and not isinstance(value, bool) and rng.random() < 0.5:
        options = [-value, 0, value * 1e6, value * 1e-6, value + 0.5, math.nan]
        options.append(float(value) if isinstance(value, int) else int(value))
        return rng.choice(options)
    return copy.deepcopy(rng.choice(HOSTILE))


def _mutate_data(data: Any, rng: random.Random, written: dict) -> str:
    """One change of the document in place, noted in `written`; what it did."""
    paths = _paths(data)
    kind = rng.choice(["swap", "swap", "swap", "delete", "add"])
    if kind == "swap":
        path = rng.choice(paths)
        value = _other_value(_parent(data, path)[path[-1]], rng)
        _parent(data, path)[path[-1]] = value
        for inner in [p for p in written if p[: len(path)] == path]:
            del written[inner]  # an earlier change inside what this one replaced is gone
        written[path] = value
        return f"{_dotted(path)} := {_short(value)}"
    if kind == "delete":
        path = rng.choice(paths)
        del _parent(data, path)[path[-1]]
        for moved in [p for p in written if p[: len(path) - 1] == path[:-1]]:
            del written[moved]  # gone, or shifted along its list
        return f"delete {_dotted(path)}"
    mappings = [()] + [p for p in paths if isinstance(_parent(data, p)[p[-1]], dict)]
    where = rng.choice(mappings)
    key = f"bogus_{rng.randrange(100)}"
    value = copy.deepcopy(rng.choice(HOSTILE))
    _parent(data, (*where, key))[key] = value
    written[(*where, key)] = value
    return f"add {_dotted((*where, key))}"


def _nested(depth: int) -> list[Any]:
    value: list[Any] = []
    for _ in range(depth - 1):
        value = [value]
    return value


def generate(seed: int) -> Case:
    """Case `seed`: a base document and one or two changes of it."""
    rng = random.Random(seed)
    base = rng.choice(sorted(BASES))
    data = copy.deepcopy(BASES[base])
    kind = rng.choice(["data"] * 6 + ["raw", "raw", "deep", "bytes", "duplicate"])
    written: dict[tuple[Any, ...], Any] = {}
    if kind == "data":
        what = "; ".join(_mutate_data(data, rng, written) for _ in range(rng.choice([1, 1, 2])))
        return Case(f"{seed} {base}: {what}", base, dump(data).encode(), written, data=data)
    if kind in ("raw", "deep"):  # a scalar written raw into the text
        leaves = [p for p in _paths(data) if not isinstance(_parent(data, p)[p[-1]], dict | list)]
        path = rng.choice(leaves)
        if kind == "raw":
            token, value = rng.choice(RAW)
        else:
            depth = rng.choice(DEPTHS)
            token = "[" * depth + "]" * depth
            value = REJECT if len(path) + depth > MAX_DEPTH else _nested(depth)
        _parent(data, path)[path[-1]] = "@@here@@"
        text = dump(data).replace('"@@here@@"', token)
        name = f"{seed} {base}: {_dotted(path)} written as {_short(token)}"
        return Case(name, base, text.encode(), {path: value}, must_reject=value is REJECT)
    text = dump(data).encode()
    if kind == "bytes":
        at = rng.randrange(len(text))
        bad = rng.choice(NOT_TEXT)
        name = f"{seed} {base}: {bad!r} at byte {at}"
        return Case(name, base, text[:at] + bad + text[at:], must_reject=True)
    lines = text.decode().splitlines(keepends=True)
    i = rng.choice([i for i, line in enumerate(lines) if re.match(r'\s*"[^"]+":', line)])
    lines.insert(i, lines[i])  # a key given twice
    name = f"{seed} {base}: line {i + 1} twice"
    return Case(name, base, "".join(lines).encode(), must_reject=True)


def checked(path: Path) -> tuple[int, str, str]:
    """check-config in this process: exit code, stdout, stderr."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = check_config(str(path))
    return code, out.getvalue(), err.getvalue()


def held_by_daemon(path: Path, base: str) -> Any:
    """The accepted file as the daemon holds it: a mapping from the first key of a path to
    the validated object (a robot file: its RobotSpec)."""
    if base == "robot":
        return Robot.from_yaml(path).spec
    config = load_checked(str(path))
    sections = {
        "controller": config.controller,
        "drives": config.drives,
        "zenoh": config.zenoh,
        "sim": sim_section(config),
        "robot": config.robot.spec if isinstance(config.raw.robot, dict) else config.raw.robot,
    }
    names = type(config.raw).model_fields
    return {name: sections.get(name, getattr(config.raw, name)) for name in names}


def at(node: Any, path: tuple[Any, ...]) -> Any:
    for part in path:
        node = getattr(node, part) if isinstance(node, BaseModel) else node[part]
    return node


def same(written: Any, held: Any) -> bool:
    """`held` is `written`: the same type and value (NaN is NaN), containers alike
    (a list may be held as a tuple, a mapping as a model with those fields), an integer
    written where a float is expected held as that float."""
    if isinstance(written, dict):
        if isinstance(held, BaseModel):
            fields = type(held).model_fields
            return all(k in fields and same(v, getattr(held, k)) for k, v in written.items())
        return isinstance(held, dict) and all(
            k in held and same(v, held[k]) for k, v in written.items()
        )
    if isinstance(written, list):
        return (
            isinstance(held, list | tuple)
            and len(held) == len(written)
            and all(same(w, h) for w, h in zip(written, held, strict=True))
        )
    if isinstance(held, enum.Enum):
        held = held.value
    if type(written) is int and type(held) is float:
        return float(written) == held
    if type(written) is float and math.isnan(written):
        return type(held) is float and math.isnan(held)
    return type(written) is type(held) and written == held


def _problem_lines(err: str, path: Path) -> str | None:
    """None if every line is 'error: FILE: ...' (the file, or the robot file it names)."""
    lines = err.splitlines()
    if not lines:
        return "exit code 1 without a message"
    for line in lines:
        if not (line.startswith(f"error: {path}: ") or line.startswith(f"error: {ROBOT_FILE}: ")):
            return f"not an 'error: FILE: ...' line: {line!r}"
    return None


def _check(case: Case, path: Path) -> tuple[int | None, str | None]:
    """check-config's exit code for `case`, and the problem with it (None: none)."""
    path.write_bytes(case.text)
    try:
        code, _out, err = checked(path)
    except (Exception, SystemExit):  # any exception at all is the finding
        return None, "raised:\n" + traceback.format_exc(limit=-4)
    if code not in (0, 1):
        return code, f"exit code {code}"
    if code == 1:
        return code, _problem_lines(err, path)
    if case.must_reject:
        return code, "accepted a file the loader must refuse"
    if case.data is not None and not same(case.data, load_yaml(path)):
        return code, "the dumped document does not read back as written"
    held = held_by_daemon(path, case.base)
    for key, value in case.written.items():
        try:
            found = at(held, key)
        except (AttributeError, KeyError, IndexError, TypeError):
            return code, f"{_dotted(key)}: accepted but not held"
        if not same(value, found):
            return code, f"{_dotted(key)}: written {_short(value)}, held {_short(found)}"
    return code, None


@pytest.mark.slow  # over 10 s of the default run's 10 minutes
@pytest.mark.timeout(120)
def test_no_traceback_and_no_silent_coercion_in_hundreds_of_mutated_configs(
    tmp_path: Path,
) -> None:
    problems, accepted = [], 0
    for seed in range(CASES):
        case = generate(seed)
        code, problem = _check(case, tmp_path / f"case{seed}.yaml")
        accepted += code == 0
        if problem is not None:
            problems.append(f"{case.name}: {problem}")
    assert not problems, f"{len(problems)} of {CASES} cases:\n" + "\n".join(problems[:25])
    assert CASES // 20 < accepted < CASES // 2  # both verdicts are exercised


@pytest.mark.slow  # over 4.5 s
@pytest.mark.timeout(120)
def test_check_config_as_a_process_agrees_with_the_in_process_verdicts(tmp_path: Path) -> None:
    """Every 100th case, and the first the loader accepts and the first it refuses,
    through `python -m daemon.cli check-config`: the same exit code and error lines as in
    this process, and no traceback (every 100th alone once drew four refusals, after a
    key added to the shipped robot file moved every case's mutation)."""
    seeds = set(range(0, CASES, 100))
    first: dict[int, int] = {}
    for seed in range(CASES):
        if len(first) == 2:
            break
        path = tmp_path / f"scan{seed}.yaml"
        path.write_bytes(generate(seed).text)
        first.setdefault(checked(path)[0], seed)
    runs = []
    for seed in sorted(seeds | set(first.values())):
        path = tmp_path / f"case{seed}.yaml"
        path.write_bytes(generate(seed).text)
        command = [sys.executable, "-m", "daemon.cli", "check-config", str(path)]
        proc = subprocess.Popen(
            command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        runs.append((seed, path, proc))
    verdicts = set()
    for seed, path, proc in runs:
        _out, err = proc.communicate(timeout=60)
        code, _, expected = checked(path)
        assert "Traceback" not in err, f"case {seed}: {err}"
        assert (proc.returncode, err) == (code, expected), f"case {seed}"
        verdicts.add(code)
    assert verdicts == {0, 1}
