"""The configuration reference, docs/configuration.md, generated from :mod:`imagine.config`.

Every field of each config dataclass with its type, default and documentation: the string
literal that follows the field in the class body (an attribute docstring, which Python drops at
runtime, so the module's source is parsed with :mod:`ast`), and the presets side by side. A field
without such a docstring is an error, so none goes undocumented. Regenerate the page with
``python -m imagine.config_reference > docs/configuration.md``; a test checks it is current.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import re
from dataclasses import dataclass
from typing import Any

from imagine import config

COMMAND = "python -m imagine.config_reference > docs/configuration.md"
_MISSING = object()


@dataclass(frozen=True)
class FieldDoc:
    """One field of a config dataclass as its source writes it."""

    name: str
    type: str
    doc: str


def _is_dataclass(node: ast.ClassDef) -> bool:
    def name(d: ast.expr) -> str:
        d = d.func if isinstance(d, ast.Call) else d
        return d.attr if isinstance(d, ast.Attribute) else getattr(d, "id", "")

    return any(name(d) == "dataclass" for d in node.decorator_list)


def config_classes(source: str) -> dict[str, ast.ClassDef]:
    """The top-level dataclasses of ``source``, AgentConfig first, the others in source order."""
    tree = ast.parse(source)
    found = {n.name: n for n in tree.body if isinstance(n, ast.ClassDef) and _is_dataclass(n)}
    return dict(sorted(found.items(), key=lambda item: item[0] != "AgentConfig"))


def markdown(doc: str) -> str:
    """A docstring as one Markdown paragraph: whitespace collapsed, reST roles (``:mod:``...)
    and double-backquoted literals as code spans."""
    text = re.sub(r":[a-z]+:`~?([^`]+)`", r"`\1`", " ".join(doc.split()))
    return text.replace("``", "`")


def field_docs(node: ast.ClassDef) -> list[FieldDoc]:
    """The annotated fields of a class body, each with the docstring that follows it (as
    :func:`markdown`); a ValueError names a field without one."""
    docs, body = [], node.body
    for i, stmt in enumerate(body):
        if not (isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name)):
            continue
        after = body[i + 1] if i + 1 < len(body) else None
        if not (
            isinstance(after, ast.Expr)
            and isinstance(after.value, ast.Constant)
            and isinstance(after.value.value, str)
        ):
            raise ValueError(f"{node.name}.{stmt.target.id} has no docstring under it")
        docs.append(
            FieldDoc(stmt.target.id, ast.unparse(stmt.annotation), markdown(after.value.value))
        )
    return docs


def _default(f: dataclasses.Field[Any]) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return _MISSING


def _code(value: Any, table: bool = False) -> str:
    return "`" + (repr(value).replace("|", "\\|") if table else repr(value)) + "`"


def _presets_table(cls: type, presets: dict[str, Any], methods: bool) -> list[str]:
    """One row per field any preset sets, one column per preset (and method where they
    differ); a value only where it differs from the default."""
    defaults = {f.name: _default(f) for f in dataclasses.fields(cls)}
    columns: list[tuple[str, dict[str, Any] | None]] = []
    for preset, by_method in presets.items():
        variants = by_method if methods else {"": by_method}
        if not any(variants.values()):
            columns.insert(0, (f"{preset} (default)", None))
        elif len({repr(v) for v in variants.values()}) == 1:
            columns.append((preset, next(iter(variants.values()))))
        else:
            columns += [(f"{preset} {m}".strip(), v) for m, v in variants.items()]
    set_anywhere = {name for _, v in columns if v for name in v}
    rows = [name for name in defaults if name in set_anywhere]
    lines = ["| field | " + " | ".join(label for label, _ in columns) + " |"]
    lines.append("| --- " * (len(columns) + 1) + "|")
    for name in rows:
        cells = [
            _code(defaults[name], table=True)
            if values is None
            else _code(values[name], table=True)
            if name in values and values[name] != defaults[name]
            else "—"
            for _, values in columns
        ]
        lines.append(f"| `{name}` | " + " | ".join(cells) + " |")
    return lines


def _encoder_presets() -> list[str]:
    """One line per (preset, encoder) of ``ENCODER_PRESETS``: what it sets over its column."""
    lines = [""]
    for preset, by_encoder in config.ENCODER_PRESETS.items():
        for encoder, values in by_encoder.items():
            settings = ", ".join(f"`{k}` {_code(v)}" for k, v in values.items())
            lines.append(f"With `encoder: {encoder}` the {preset} augmented agent sets over its "
                         f"column (`ENCODER_PRESETS`): {settings}.")  # fmt: skip
    return lines


PRESET_TABLES = {"AgentConfig": ("AGENT_PRESETS", True), "VisionConfig": ("VISION_PRESETS", False)}
"""Which preset mapping of :mod:`imagine.config` each class's table shows, and whether it holds
one entry per method (baseline, augmented)."""


def configuration_markdown() -> str:
    """docs/configuration.md: every config dataclass of :mod:`imagine.config`, its presets side
    by side and its fields with their types, defaults and docstrings."""
    out = [
        "# Configuration reference",
        "",
        f"*Generated by `{COMMAND}` from the field docs of `src/imagine/config.py`; do not edit "
        "by hand.*",
        "",
        "Any field can be set with `--set KEY=VALUE` or in a `--config FILE.yaml` "
        "(see [guide.md](guide.md)).",
    ]
    for name, node in config_classes(inspect.getsource(config)).items():
        cls = getattr(config, name)
        docs = field_docs(node)
        runtime = [f.name for f in dataclasses.fields(cls)]
        if [d.name for d in docs] != runtime:
            raise ValueError(f"{name}: the source's fields differ from the class's {runtime}")
        out += ["", f"## {name}", "", markdown(inspect.getdoc(cls) or "")]
        if name in PRESET_TABLES:
            mapping, methods = PRESET_TABLES[name]
            out += ["", f"### Presets (`{mapping}`)", "", "—: the default.", ""]
            out += _presets_table(cls, getattr(config, mapping), methods)
            if name == "AgentConfig":
                out += _encoder_presets()
        out += ["", "### Fields", ""]
        defaults = {f.name: _default(f) for f in dataclasses.fields(cls)}
        for d in docs:
            default = "" if defaults[d.name] is _MISSING else f" = {_code(defaults[d.name])}"
            out.append(f"- **`{d.name}`**: `{d.type}`{default}. {d.doc}")
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    print(configuration_markdown(), end="")
