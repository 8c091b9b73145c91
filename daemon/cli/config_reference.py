"""The config reference page, written from the config models themselves so that it cannot
drift from the code: `python -m daemon.cli.config_reference > docs/reference/config.md`
(tests/test_docs.py fails while the committed page differs).

Each section is a pydantic model (cdpr.description.StrictModel): its docstring is the
section's text, and a table gives every key with its type, default and limits as the
model declares them.  A key's description is, in this order, its string literal after
the field (an attribute docstring), its comment (on its line, or the lines just above),
or its own line in the class docstring ("key: what it is", or "a / b: ..." for two)."""

from __future__ import annotations

import ast
import enum
import inspect
import io
import re
import textwrap
import tokenize
import types
import typing
from collections.abc import Iterator
from typing import Any

import annotated_types
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from cdpr.control_spec import ControllerSpec
from cdpr.description import RobotSpec
from daemon.config import FileConfig
from daemon.config.ros2_config import Ros2Settings
from daemon.config.zenoh_config import ZenohSettings
from drivers.config import CanConfig, DrivesConfig
from sim_bus.config import SimConfig

# sections the file keeps as raw data and validates later, against these models
VALIDATED_LATER: dict[str, type[BaseModel]] = {
    "robot": RobotSpec,
    "controller": ControllerSpec,
    "drives": DrivesConfig,
    "can": CanConfig,
    "zenoh": ZenohSettings,
    "sim": SimConfig,
    "ros2": Ros2Settings,
}
_KEY_LINE = re.compile(r"^([a-z_][a-z0-9_]*(?:\s*/\s*[a-z_][a-z0-9_]*)*):\s+(.*)$")
_LIMITS = (
    (annotated_types.Gt, "gt", "> {}"),
    (annotated_types.Ge, "ge", ">= {}"),
    (annotated_types.Lt, "lt", "< {}"),
    (annotated_types.Le, "le", "<= {}"),
    (annotated_types.MinLen, "min_length", "at least {} long"),
    (annotated_types.MaxLen, "max_length", "at most {} long"),
)


def key_descriptions(model: type[BaseModel]) -> dict[str, str]:
    """Each key's description (module docstring): from the source of the model and of
    the models it derives from, else from its docstring."""
    found = _split_docstring(model)[1]
    for cls in reversed(model.__mro__):
        if issubclass(cls, BaseModel) and cls.__module__.split(".")[0] != "pydantic":
            found.update(_source_descriptions(cls))
    return found


def _source_descriptions(cls: type) -> dict[str, str]:
    """Field name -> the string literal after it, else its comment (same line, or the
    comment lines right above it), from the class's source."""
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    comments: dict[int, str] = {}
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            comments[token.start[0]] = token.string.lstrip("#").strip()
    lines = source.splitlines()
    body = ast.parse(source).body[0]
    assert isinstance(body, ast.ClassDef)
    found: dict[str, str] = {}
    for i, node in enumerate(body.body):
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        after = body.body[i + 1] if i + 1 < len(body.body) else None
        if (
            isinstance(after, ast.Expr)
            and isinstance(after.value, ast.Constant)
            and isinstance(after.value.value, str)
        ):
            found[node.target.id] = " ".join(inspect.cleandoc(after.value.value).split())
            continue
        end = node.end_lineno or node.lineno
        if end in comments and not lines[end - 1].lstrip().startswith("#"):
            found[node.target.id] = comments[end]
            continue
        above: list[str] = []
        line = node.lineno - 1
        while line in comments and lines[line - 1].lstrip().startswith("#"):
            above.insert(0, comments[line])
            line -= 1
        if above:
            found[node.target.id] = " ".join(above)
    return found


def _split_docstring(model: type[BaseModel]) -> tuple[str, dict[str, str]]:
    """The model's docstring as prose and key lines: a line "key: text" (or "a / b:
    text") and the more-indented lines after it describe those keys; the rest is the
    section's text."""
    prose: list[str] = []
    found: dict[str, str] = {}
    keys: list[str] = []
    for line in inspect.cleandoc(model.__doc__ or "").splitlines():
        match = _KEY_LINE.match(line)
        named = [k.strip() for k in match[1].split("/")] if match else []
        if named and all(k in model.model_fields for k in named):
            keys = named
            for key in keys:
                found[key] = match[2].strip()
        elif keys and line.startswith((" ", "\t")):
            for key in keys:
                found[key] += " " + line.strip()
        else:
            keys = []
            prose.append(line)
    return "\n".join(prose).strip(), found


def _type_name(annotation: Any) -> str:
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _type_name(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(annotation))
    if origin is typing.Literal:
        values = typing.get_args(annotation)
        return " or ".join(f'"{a}"' if isinstance(a, str) else str(a) for a in values)
    if origin in (list, tuple):
        args = [a for a in typing.get_args(annotation) if a is not Ellipsis]
        return f"list of {_type_name(args[0])}" if args else "list"
    if origin is dict:
        return "mapping"
    if annotation is type(None):
        return "null"
    if isinstance(annotation, type) and issubclass(annotation, enum.Enum):
        return " or ".join(f'"{m.value}"' for m in annotation)
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return "section"
    return getattr(annotation, "__name__", str(annotation))


def _limits(info: FieldInfo) -> str:
    """The bounds the field's own metadata (and its Annotated types') declare."""
    found: list[str] = []

    def visit(metadata: list[Any]) -> None:
        for item in metadata:
            for kind, attribute, text in _LIMITS:
                if isinstance(item, kind):
                    found.append(text.format(getattr(item, attribute)))
            if isinstance(item, FieldInfo):
                visit(item.metadata)

    visit(info.metadata)
    for arg in _annotated_parts(info.annotation):
        visit(arg)
    return ", ".join(dict.fromkeys(found))


def _annotated_parts(annotation: Any) -> Iterator[list[Any]]:
    """The metadata of Annotated types inside unions and lists of `annotation`."""
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        base, *metadata = typing.get_args(annotation)
        yield list(metadata)
        yield from _annotated_parts(base)
    elif origin in (typing.Union, types.UnionType, list, tuple):
        for arg in typing.get_args(annotation):
            yield from _annotated_parts(arg)


def _default(info: FieldInfo) -> str:
    if info.default_factory is not None:
        value = info.default_factory()
    elif info.default is PydanticUndefined:
        return "required"
    else:
        value = info.default
    return _yaml(value)


def _yaml(value: Any) -> str:
    if isinstance(value, BaseModel):
        return "(below)"
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, enum.Enum):
        return str(value.value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_yaml(v) for v in value) + "]" if value else "[]"
    if isinstance(value, dict):
        return "{}" if not value else str(value)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def section_of(model: type[BaseModel], name: str) -> type[BaseModel] | None:
    """The section model key `name` of `model` holds, if any: for the file's top level
    also the sections it keeps as raw data (VALIDATED_LATER)."""
    if model is FileConfig and name in VALIDATED_LATER:
        return VALIDATED_LATER[name]
    return _nested(model.model_fields[name].annotation)


def _nested(annotation: Any) -> type[BaseModel] | None:
    """The section model a key holds (alone, optional, or as a list of them), if any."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        found = _nested(arg)
        if found is not None:
            return found
    return None


def section(key: str, model: type[BaseModel], depth: int = 2) -> list[str]:
    """Markdown for the section `key` (model `model`) and the sections inside it."""
    described = key_descriptions(model)
    lines = [f"{'#' * depth} " + (key if model is FileConfig else f"`{key}`"), ""]
    prose = _split_docstring(model)[0]
    if prose:
        lines += [prose, ""]
    lines += ["| key | type | default | limits | description |", "|---|---|---|---|---|"]
    inner: list[tuple[str, type[BaseModel]]] = []
    for name, info in model.model_fields.items():
        kind = _type_name(info.annotation)
        nested = section_of(model, name)
        if nested is not None:
            inner.append((f"{key}.{name}" if model is not FileConfig else name, nested))
            kind = kind.replace("mapping", "section")
        default = _default(info)
        if nested is not None and default != "required":
            default = "(below)"
        cells = (f"`{name}`", kind, default, _limits(info), described.get(name, ""))
        lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    lines.append("")
    for name, nested in inner:
        lines += section(name, nested, min(depth + 1, 4) if model is not FileConfig else 2)
    return lines


def config_reference() -> str:
    """Markdown: the config file's keys, section by section."""
    parts = [
        "# Config reference",
        "",
        "Written from the config models by `python -m daemon.cli.config_reference`; every key, "
        "its type, default and limits as the daemon checks them (`cdprd check-config FILE` "
        "runs the same checks).",
        "",
    ]
    parts += section("Top level", FileConfig, 2)
    return "\n".join(parts).rstrip() + "\n"


if __name__ == "__main__":
    print(config_reference(), end="")
