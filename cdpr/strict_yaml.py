"""YAML for config files: the YAML 1.2 core schema, strictly, within bounds.

PyYAML's SafeLoader reads YAML 1.1, where `8:20` is the base-60 integer 500, `yes`, `no`,
`on` and `off` are booleans, `1_000` is 1000, `017` is octal and `2001-12-14` a date: a
config would hold a value its author never wrote.  Here plain scalars resolve as in the
YAML 1.2 core schema (null, true/false, decimal, 0o and 0x integers, decimal floats, .inf,
.nan) and everything else is a string; only the core tags construct (`!!binary`,
`!!timestamp`, `!!set`, ... are refused, never read as something else); mapping keys are
strings and unique; `<<` is a plain key, not a merge.

Bounds keep a hostile document from costing a RecursionError, memory or minutes: nesting
depth, nodes after alias expansion, integers within 64 bits, floats within range.  The
caller bounds the text's size.  Every problem raises a yaml.MarkedYAMLError with the
position; `describe` turns any yaml.YAMLError into one line.
"""

from __future__ import annotations

import math
import re
from typing import Any

import yaml
from yaml.composer import Composer
from yaml.constructor import BaseConstructor, ConstructorError
from yaml.events import AliasEvent
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode
from yaml.parser import Parser
from yaml.reader import Reader
from yaml.resolver import BaseResolver
from yaml.scanner import Scanner

MAX_DEPTH = 64  # levels of nesting, also through aliases
INT_BOUND = 2**63  # integers must lie within (-INT_BOUND, INT_BOUND)

_TAG = "tag:yaml.org,2002:"
_NULL = re.compile(r"(?:~|null|Null|NULL|)\Z")
_TRUE = ("true", "True", "TRUE")
_FALSE = ("false", "False", "FALSE")
_BOOL = re.compile(r"(?:true|True|TRUE|false|False|FALSE)\Z")
_INT = re.compile(r"(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)\Z")
_FLOAT = re.compile(
    r"(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
    r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))\Z"
)
_SURROGATE = re.compile("[\ud800-\udfff]")
_INT_DIGITS = len(str(INT_BOUND))  # longer digit strings are out of range unconverted


class _CoreResolver(BaseResolver):
    """Implicit tags of the YAML 1.2 core schema (PyYAML's resolver is YAML 1.1's)."""


for _tag, _pattern, _first in (
    ("null", _NULL, ["~", "n", "N", ""]),
    ("bool", _BOOL, list("tTfF")),
    ("int", _INT, list("-+0123456789")),
    ("float", _FLOAT, list("-+.0123456789")),
):
    _CoreResolver.add_implicit_resolver(_TAG + _tag, _pattern, _first)


def _refuse(problem: str, node: Node) -> ConstructorError:
    return ConstructorError(None, None, problem, node.start_mark)


class _CoreConstructor(BaseConstructor):
    """Constructors of the core tags only; each checks its scalar (an explicit `!!int 1.5`
    is refused, not truncated)."""

    def construct_scalar_checked(self, node: Node, pattern: re.Pattern[str], what: str) -> str:
        value = self.construct_scalar(node)
        if not pattern.match(value):
            raise _refuse(f"{_clip(value)} is not {what}", node)
        return value

    def construct_null(self, node: Node) -> None:
        self.construct_scalar_checked(node, _NULL, "null")

    def construct_bool(self, node: Node) -> bool:
        return self.construct_scalar_checked(node, _BOOL, "true or false") in _TRUE

    def construct_int(self, node: Node) -> int:
        text = self.construct_scalar_checked(node, _INT, "an integer")
        digits = text.lstrip("+-")
        if len(digits) > _INT_DIGITS:
            raise _refuse(f"integer of {len(digits)} digits is out of range (64 bits)", node)
        value = int(text, 0) if text[:2] in ("0o", "0x") else int(text, 10)
        if not -INT_BOUND < value < INT_BOUND:
            raise _refuse(f"integer {text} is out of range (64 bits)", node)
        return value

    def construct_float(self, node: Node) -> float:
        text = self.construct_scalar_checked(node, _FLOAT, "a number")
        special = text.lstrip("+-").lower()
        if special in (".inf", ".nan"):
            value = math.inf if special == ".inf" else math.nan
            return -value if text.startswith("-") else value
        value = float(text)
        if math.isinf(value):
            raise _refuse(f"{text} is out of the range of a float", node)
        return value

    def construct_str(self, node: Node) -> str:
        if not isinstance(node, ScalarNode):
            raise _refuse(f"{_kind(node)} cannot be a string", node)
        value = self.construct_scalar(node)
        if _SURROGATE.search(value):  # only a "\ud800" escape makes one
            raise _refuse("a lone surrogate escape (\\ud800-\\udfff) is not a character", node)
        return value

    def construct_seq(self, node: Node) -> list[Any]:
        if not isinstance(node, SequenceNode):
            raise _refuse(f"{_kind(node)} cannot be a sequence", node)
        return [self.construct_object(child, deep=True) for child in node.value]

    def construct_map(self, node: Node) -> dict[str, Any]:
        if not isinstance(node, MappingNode):
            raise _refuse(f"{_kind(node)} cannot be a mapping", node)
        mapping: dict[str, Any] = {}
        for key_node, value_node in node.value:
            key = self.construct_object(key_node, deep=True)
            if not isinstance(key, str):
                what = "" if isinstance(key_node, ScalarNode) else f" ({_kind(key_node)})"
                problem = f"the mapping key {_clip(key)}{what} is not a string: quote it"
                raise _refuse(problem, key_node)
            if key in mapping:
                raise _refuse(f"duplicate key {_clip(key)}", key_node)
            mapping[key] = self.construct_object(value_node, deep=True)
        return mapping

    def construct_other(self, node: Node) -> None:
        raise _refuse(f"the tag {node.tag} is not supported (core YAML types only)", node)


for _tag, _construct in (
    ("null", _CoreConstructor.construct_null),
    ("bool", _CoreConstructor.construct_bool),
    ("int", _CoreConstructor.construct_int),
    ("float", _CoreConstructor.construct_float),
    ("str", _CoreConstructor.construct_str),
    ("seq", _CoreConstructor.construct_seq),
    ("map", _CoreConstructor.construct_map),
):
    _CoreConstructor.add_constructor(_TAG + _tag, _construct)
_CoreConstructor.add_constructor(None, _CoreConstructor.construct_other)


class _BoundedLoader(Reader, Scanner, Parser, Composer, _CoreConstructor, _CoreResolver):
    """Composes within MAX_DEPTH levels and `max_nodes` nodes counted as constructed (an
    alias counts the whole node it repeats), then constructs with the core tags."""

    def __init__(self, text: str, max_nodes: int) -> None:
        Reader.__init__(self, text)
        Scanner.__init__(self)
        Parser.__init__(self)
        Composer.__init__(self)
        _CoreConstructor.__init__(self)
        _CoreResolver.__init__(self)
        self._max_nodes = max_nodes
        self._depth = 0
        self._measured: dict[Node, tuple[int, int]] = {}  # node -> (nodes, height)

    def compose_node(self, parent: Node | None, index: Any) -> Node:
        if self._depth >= MAX_DEPTH:
            mark = self.peek_event().start_mark
            raise ConstructorError(None, None, f"nested deeper than {MAX_DEPTH} levels", mark)
        if self.check_event(AliasEvent):
            target = self.anchors.get(self.peek_event().anchor)
            if target is not None and target not in self._measured:  # still being composed
                problem = "an alias refers to a node that contains it"
                raise ConstructorError(None, None, problem, self.peek_event().start_mark)
        self._depth += 1
        try:
            node = super().compose_node(parent, index)
        finally:
            self._depth -= 1
        self._measure(node)
        return node

    def _measure(self, node: Node) -> None:
        if node in self._measured:  # an alias of a finished node
            nodes, height = self._measured[node]
        else:
            children = node.value if isinstance(node, SequenceNode) else []
            if isinstance(node, MappingNode):
                children = [part for pair in node.value for part in pair]
            sizes = [self._measured[child] for child in children]
            nodes = 1 + sum(n for n, _ in sizes)
            height = 1 + max((h for _, h in sizes), default=0)
            self._measured[node] = (nodes, height)
        if height > MAX_DEPTH:
            raise _refuse(f"nested deeper than {MAX_DEPTH} levels through aliases", node)
        if nodes > self._max_nodes:
            raise _refuse(f"more than {self._max_nodes} values once aliases are expanded", node)


def parse(text: str, max_nodes: int) -> Any:
    """The single document in `text` (None if empty); yaml.YAMLError on any problem."""
    loader = _BoundedLoader(text, max_nodes)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def describe(exc: yaml.YAMLError) -> str:
    """One line: 'line L, column C: problem (context)'."""
    if isinstance(exc, yaml.MarkedYAMLError):
        mark = exc.problem_mark or exc.context_mark
        where = "" if mark is None else f"line {mark.line + 1}, column {mark.column + 1}: "
        problem = exc.problem or "not valid YAML"
        context = f" ({exc.context})" if exc.context else ""
        if exc.context and exc.context_mark is not None and exc.context_mark is not mark:
            begun = exc.context_mark
            context = f" ({exc.context} begun at line {begun.line + 1}, column {begun.column + 1})"
        syntax = "" if isinstance(exc, ConstructorError) else "not valid YAML: "
        return _one_line(f"{where}{syntax}{problem}{context}")
    if isinstance(exc, yaml.reader.ReaderError):
        return _one_line(f"character {exc.position + 1}: not valid YAML: {exc.reason}")
    return _one_line(f"not valid YAML: {exc}")


def _one_line(text: str) -> str:
    return " ".join(text.split())

def _kind(node: Node) -> str:
    if isinstance(node, MappingNode):
        return "a mapping"
    if isinstance(node, SequenceNode):
        return "a sequence"
    return f"the scalar {_clip(node.value)}"


def _clip(value: Any, limit: int = 60) -> str:
    """repr(value), shortened to about `limit` characters."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 5] + "...'"
