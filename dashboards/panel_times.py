"""`sim2act bench panels`: each dashboard panel's query timed on a real warehouse, as the dashboard
runs it (`dashboards.panels.run_panel`: a fresh read-only connection per request), against the 1 s a
panel may take (issue 11: at a million triplets).

1. the panels of dashboards/panels.yaml, in page order;
2. per panel: one cold run (the first after opening: DuckDB reads the Parquet footers), then `repeats`
   warm runs, their median;
3. a Markdown table: rows, cold and warm ms, and whether the slower of the two is within the target.
"""

from __future__ import annotations

import statistics
import time

from pydantic import BaseModel

from dashboards.panels import load_panels, run_panel
from warehouse.catalog import Catalog

TARGET_MS = 1000.0


class PanelTime(BaseModel):
    panel: str
    rows: int
    cold_ms: float
    warm_ms: float  # median of the warm runs

    @property
    def within_target(self) -> bool:
        return max(self.cold_ms, self.warm_ms) <= TARGET_MS


def bench_panels(catalog: Catalog, campaign: str, repeats: int = 3) -> list[PanelTime]:
    """Time every panel for `campaign` (steps in the module docstring)."""
    times = []
    for panel in load_panels():
        runs = []
        for _ in range(1 + repeats):
            started = time.perf_counter()
            rows = run_panel(catalog, panel, campaign)
            runs.append((time.perf_counter() - started) * 1000)
        times.append(PanelTime(panel=panel.id, rows=len(rows.rows), cold_ms=runs[0], warm_ms=statistics.median(runs[1:])))
    return times


def markdown(times: list[PanelTime], facts: str, command_line: str) -> str:
    lines = [f"`{command_line}`: {facts}", "",
             f"| panel | rows | first run ms | warm ms (median) | ≤ {TARGET_MS:,.0f} ms |", "|---|---|---|---|---|"]
    lines += [f"| {t.panel} | {t.rows:,} | {t.cold_ms:,.0f} | {t.warm_ms:,.0f} | {'yes' if t.within_target else 'NO'} |"
              for t in times]
    return "\n".join(lines) + "\n"
