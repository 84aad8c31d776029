"""The stages of a bootstrap iteration, one module each: generate_tasks, explore, filter, index,
train, evaluate, redeploy, and the campaign's last two, baselines and adapt. Plain typed functions,
no Prefect inside (flows/ wraps them). This module is the contract they share:

- work comes in **units**, each keyed by `schemas.keys.unit_key` over exactly what it reads;
- a unit whose key is registered in the catalog is skipped, never redone (`StageUnits.pending`,
  `StageUnits.run`);
- a finished unit is registered atomically, its shards and catalog rows with it
  (`StageUnits.register`): a kill loses at most the unit in flight;
- every `run_<stage>` returns a `StageResult`, whose `did_work()`, `metrics()`, `tags()` and
  `artifacts()` say what this run did (nothing when every unit was registered already: a re-run logs no second point),
  so the flow logs every stage alike.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel

from warehouse.catalog import Catalog
from warehouse.shard_writer import ShardFile


class StageResult(BaseModel):
    """What a `run_<stage>` returns. `did_work` every stage says; the hooks below are empty by
    default, and a stage overrides those it has something for."""

    def did_work(self) -> bool:
        """Whether this run did any unit's work (False: every unit was registered already)."""
        raise NotImplementedError(f"{type(self).__name__} does not say whether it did work")

    def metrics(self) -> dict[str, float]:
        """MLflow metrics of the work this run did ({} when it did none)."""
        return {}

    def tags(self) -> dict[str, str]:
        """MLflow tags of the iteration run ({} when the run did no work)."""
        return {}

    def artifacts(self) -> list[tuple[str, str]]:
        """(file, folder) pairs for the iteration run: files this run made."""
        return []


@dataclass
class UnitOutput:
    """What one unit's work hands to the catalog."""

    summary: Mapping[str, Any]  # stage_runs.summary: the unit's figures, as JSON
    shards: Sequence[ShardFile] = ()
    rows: Mapping[str, Sequence[Mapping[str, Any]]] | None = None  # catalog table -> rows, registered with it
    earlier_wall_s: float = 0.0  # compute spent on this unit by runs a kill interrupted
    value: Any = field(default=None)  # whatever the stage wants back from the work (not registered)


@dataclass(frozen=True)
class StageUnits:
    """One stage's units in one campaign iteration: which are pending, and registering them."""

    catalog: Catalog
    stage: str
    campaign: str
    iteration: int

    def pending(self, keys: Iterable[str]) -> list[str]:
        """The keys not registered yet, in the order given."""
        keys = list(keys)
        done = self.catalog.registered_keys(keys)
        return [key for key in keys if key not in done]

    def register(self, key: str, output: UnitOutput, wall_s: float) -> None:
        """Commit one finished unit (its stage_runs row, shards and rows) atomically."""
        self.catalog.register_unit(unit_key=key, stage=self.stage, campaign=self.campaign, iteration=self.iteration,
                                   summary=output.summary, wall_s=wall_s + output.earlier_wall_s,
                                   shards=output.shards, rows=output.rows)

    def run(self, key: str, work: Callable[[], UnitOutput]) -> UnitOutput | None:
        """key registered? None (skipped) : run `work`, register what it made, return it."""
        if self.catalog.is_registered(key):
            return None
        started = time.monotonic()
        output = work()
        self.register(key, output, time.monotonic() - started)
        return output
