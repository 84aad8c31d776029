"""A campaign config as YAML a person reads and `--config` loads back (`sim2act config`): every field with its
value, its description above it as a comment, each section under its model's first docstring line."""

from __future__ import annotations

import textwrap

import yaml
from pydantic import BaseModel

from schemas.config import CampaignConfig, load_config

WIDTH = 110  # a comment's lines wrap here


def config_yaml(config: CampaignConfig, changed: bool = False, said: str = "") -> str:
    """`config` as commented YAML: `sim2act run --config FILE` (no preset) makes the same campaign again.

    Args:
        config: the resolved campaign config.
        changed: only the fields whose value differs from the default preset's, the one `--config` lands on
            (a section appears where one of its fields does).
        said: the command that resolved it, for the header.

    Returns:
        The YAML text, ending in a newline.
    """
    base = load_config("default") if changed else None
    header = [f"# {said}" if said else "# a sim2act campaign config",
              "# run it: sim2act run --config THIS_FILE (every setting is here: no --preset needed)"
              if not changed else
              "# the fields that differ from the default preset; run it: sim2act run --config THIS_FILE (no --preset)"]
    # dumped once, as YAML writes enums, paths and tuples; each section reads its part
    return "\n".join([*header, *_fields(config, config.model_dump(mode="json"), base, 0)]) + "\n"


def _fields(model: BaseModel, values: dict, base: BaseModel | None, depth: int) -> list[str]:
    """`model`'s fields (`values`: its JSON dump) as YAML lines at `depth`; with `base`, only those that differ."""
    pad = "  " * depth
    lines: list[str] = []
    for name, field in type(model).model_fields.items():
        value, other = getattr(model, name), None if base is None else getattr(base, name)
        if base is not None and value == other:
            continue
        about = field.description or (_first_line(type(value).__doc__) if isinstance(value, BaseModel) else "")
        lines += [f"{pad}# {line}" for line in textwrap.wrap(about, WIDTH - len(pad) - 2, break_on_hyphens=False,
                                                              break_long_words=False)]
        if isinstance(value, BaseModel):
            # a section that was None under the base (an optional one set here) is written whole
            inner = _fields(value, values[name], other if isinstance(other, BaseModel) else None, depth + 1)
            lines += [f"{pad}{name}:", *inner]
        else:
            lines += _flow_lines(f"{pad}{name}: ", values[name], pad + "    ")
    return lines


def _flow_lines(start: str, value, indent: str) -> list[str]:
    """`start` and the value in flow style; a long list or mapping goes on over lines at `indent` (deeper
    than its key, as YAML reads a flow collection's line breaks)."""
    if isinstance(value, (list, dict)) and value:
        opening, closing = ("[", "]") if isinstance(value, list) else ("{", "}")
        items = [_flow(v) for v in value] if isinstance(value, list) else \
            [f"{_flow(k)}: {_flow(v)}" for k, v in value.items()]
        lines, line, holds_item = [], start + opening, False
        for i, item in enumerate(items):
            piece = item + (", " if i < len(items) - 1 else closing)
            if holds_item and len(line) + len(piece.rstrip()) > WIDTH:
                lines.append(line.rstrip())
                line = indent
            line, holds_item = line + piece, True
        return [*lines, line]
    return [start + _flow(value)]


def _flow(value) -> str:
    """One value on one line: scalars as YAML reads them back, lists and mappings in flow style."""
    text = yaml.safe_dump(value, default_flow_style=True, width=10**6, sort_keys=False).strip()
    return text.removesuffix("...").strip()  # a bare scalar's document end marker


def _first_line(doc: str | None) -> str:
    """A docstring's first paragraph on one line."""
    return " ".join((doc or "").strip().split("\n\n")[0].split())
