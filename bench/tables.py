"""What every bench reports through: one Markdown table writer, and the ratios against their targets."""

from __future__ import annotations

import os

from pydantic import BaseModel


class Ratio(BaseModel):
    """One figure against its reference (or a fraction, or a latency), with the target it must meet."""

    name: str
    value: float
    unit: str = "x"  # x (a ratio), % (a fraction, shown as a percentage) or ms
    target: float | None = None
    at_most: bool = False  # the target is an upper bound
    met: bool | None = None  # None: no target

    @classmethod
    def of(cls, name: str, value: float, target: float | None = None, unit: str = "x", at_most: bool = False) -> Ratio:
        met = None if target is None else (value <= target if at_most else value >= target)
        return cls(name=name, value=value, unit=unit, target=target, at_most=at_most, met=met)

    def shown(self, value: float) -> str:
        return f"{value:.1%}" if self.unit == "%" else f"{value:.1f} ms" if self.unit == "ms" else f"{value:.2f}"


def table(header: list[str], rows: list[list[object]]) -> list[str]:
    """A Markdown table's lines; None cells are left empty."""
    cells = [["" if cell is None else str(cell) for cell in row] for row in rows]
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header), *("| " + " | ".join(row) + " |" for row in cells)]


def ratio_table(ratios: list[Ratio]) -> list[str]:
    return table(["ratio", "value", "target", "met"], [
        [r.name, r.shown(r.value), "" if r.target is None else ("<= " if r.at_most else ">= ") + r.shown(r.target),
         "" if r.met is None else "✓" if r.met else "✗"]
        for r in ratios])


def cores() -> int:
    """The cores this process may run on (its affinity: `taskset` and cpusets count, os.cpu_count() counts every
    core; a CPU quota, `docker --cpus`, is not seen)."""
    return len(os.sched_getaffinity(0))
