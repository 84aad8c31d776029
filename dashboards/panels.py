"""The dashboard's panels: each one SQL query against the catalog and how to draw its rows,
declared in panels.yaml, checked here before the server starts."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import duckdb
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from dashboards.reads import Rows, read_rows
from schemas.errors import Sim2ActError
from warehouse.catalog import Catalog
from warehouse.sql import check_read_only

PANELS_FILE = Path(__file__).with_name("panels.yaml")
# What a panel's SQL may name as `$parameter`: the page fills these in.
PARAMETERS = frozenset({"campaign"})


class PanelError(Sim2ActError, ValueError):
    """A panel that cannot be used; the message names the file, the panel and the reason."""


class Panel(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    id: str = Field(pattern=r"^[a-z][a-z0-9_]*$")
    title: str
    kind: Literal["line", "bar", "table"]
    sql: str
    description: str = ""
    x: str | None = None
    y: str | None = None
    series: str | None = None
    low: str | None = None
    high: str | None = None
    percent: list[str] = []
    horizontal: bool = False
    wide: bool = False

    @model_validator(mode="after")
    def _fits_its_kind(self) -> Panel:
        if self.kind != "table" and not (self.x and self.y):
            raise ValueError(f"a {self.kind} chart needs x and y columns")
        if (self.low is None) != (self.high is None) or (self.low and self.kind != "line"):
            raise ValueError("low and high come together, on a line chart")
        if self.horizontal and self.kind != "bar":
            raise ValueError("horizontal is for bar charts")
        check_read_only(self.sql)
        unknown = self.parameters - PARAMETERS
        if unknown:
            raise ValueError(f"unknown SQL parameter(s) {', '.join(sorted(unknown))} (known: ${', $'.join(PARAMETERS)})")
        return self

    @property
    def parameters(self) -> set[str]:
        return set().union(*(s.named_parameters for s in duckdb.extract_statements(self.sql)))

    @property
    def columns(self) -> list[str]:
        """The columns its drawing needs from the rows."""
        return [c for c in (self.x, self.y, self.series, self.low, self.high) if c]


def load_panels(path: Path = PANELS_FILE) -> list[Panel]:
    """The panels of a YAML file, in page order; a bad one is refused naming it and the reason."""
    try:
        document = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise PanelError(f"{path}: {exc}") from None
    if not isinstance(document, dict) or set(document) != {"panels"} or not isinstance(document["panels"], list):
        raise PanelError(f"{path}: expected one key, `panels:`, holding a list of panels")
    panels = []
    for index, entry in enumerate(document["panels"]):
        name = entry.get("id", f"#{index + 1}") if isinstance(entry, dict) else f"#{index + 1}"
        try:
            panels.append(Panel.model_validate(entry))
        except ValidationError as exc:
            error = exc.errors()[0]
            where = ".".join(str(p) for p in error["loc"])
            message = error["msg"].removeprefix("Value error, ")
            raise PanelError(f"{path}: panel {name}: {where + ': ' if where else ''}{message}") from None
    ids = [p.id for p in panels]
    if duplicated := sorted({i for i in ids if ids.count(i) > 1}):
        raise PanelError(f"{path}: panel id(s) used twice: {', '.join(duplicated)}")
    return panels


def run_panel(catalog: Catalog, panel: Panel, campaign: str) -> Rows:
    """The panel's rows for a campaign; a query that lacks a column its chart draws is refused."""
    rows = read_rows(catalog, panel.sql, {name: campaign for name in panel.parameters})
    missing = [c for c in panel.columns if c not in rows.columns]
    if missing:
        raise PanelError(f"panel {panel.id}: its SQL returns no column {', '.join(missing)} "
                         f"(it returns {', '.join(rows.columns)})")
    return rows
