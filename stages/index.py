"""index: the iteration's snapshot of the warehouse. Aggregates this iteration's kept data with
every earlier iteration's, and fixes the training selection and its digest."""

from __future__ import annotations

import logging
import time

from schemas.config import CampaignConfig
from schemas.errors import Sim2ActError
from schemas.keys import unit_key
from schemas.workspace import Workspace
from stages import StageResult, StageUnits, UnitOutput
from stages.filter import filter_unit_key
from warehouse.catalog import Catalog
from warehouse.datasets import Selection

STAGE, VERSION = "index", 1
log = logging.getLogger("sim2act.stages.index")


class NothingToTrain(Sim2ActError, RuntimeError):
    """An iteration whose dataset is empty: said in one line (the filter's setting), nothing trained."""


class IndexResult(StageResult):
    unit_key: str
    iteration: int
    dataset_digest: str
    explore_units: list[str]
    filter_units: list[str]
    episodes: int
    kept_episodes: int
    triplets: int
    skipped: bool

    def did_work(self) -> bool:
        return not self.skipped

    def metrics(self) -> dict[str, float]:
        return {} if self.skipped else {f"dataset.{k}": getattr(self, k) for k in ("episodes", "kept_episodes", "triplets")}

    def tags(self) -> dict[str, str]:
        return {} if self.skipped else {"sim2act.dataset_digest": self.dataset_digest}

    @property
    def selection(self) -> Selection:
        return Selection(tuple(self.explore_units), tuple(self.filter_units))


def latest_index(workspace: Workspace, campaign: str, iteration: int | None = None,
                 config: CampaignConfig | None = None) -> IndexResult | None:
    """A campaign's registered dataset of `iteration` (default: its latest), or None. With `config`, only a
    dataset its filter settings decided (another filter.* makes another dataset of the same iteration); of
    several, the latest registered."""
    rows = Catalog(workspace.catalog).query(
        "SELECT i.unit_key, i.iteration, i.dataset_digest, i.explore_units, i.filter_units, i.episodes, "
        "i.kept_episodes, i.triplets FROM iterations i LEFT JOIN stage_runs r ON r.unit_key = i.unit_key "
        "WHERE i.campaign = ? AND (? IS NULL OR i.iteration = ?) "
        "ORDER BY i.iteration DESC, r.finished_at DESC NULLS LAST, i.unit_key DESC",
        [campaign, iteration, iteration],
    )
    if config is not None:
        rows = [row for row in rows if set(row[4]) == {filter_unit_key(config, explore) for explore in row[3]}]
    if not rows:
        return None
    key, it, digest, explore_units, filter_units, episodes, kept, triplets = rows[0]
    return IndexResult(unit_key=key, iteration=it, dataset_digest=digest, explore_units=explore_units,
                       filter_units=filter_units, episodes=episodes, kept_episodes=kept, triplets=triplets,
                       skipped=True)


def run_index(
    workspace: Workspace,
    config: CampaignConfig,
    iteration: int,
    explore_keys: list[str],
    filter_keys: list[str],
    previous: IndexResult | None,
) -> IndexResult:
    """Unit of work: the iteration's dataset, keyed by every explore and filter unit of iterations
    0..`iteration`. Registers an `iterations` row: the selection, its digest and its counts."""
    catalog = Catalog(workspace.catalog)
    explore_units = sorted(set(explore_keys) | set(previous.explore_units if previous else ()))
    filter_units = sorted(set(filter_keys) | set(previous.filter_units if previous else ()))
    key = unit_key(STAGE, VERSION, {"campaign": config.name, "iteration": iteration}, explore_units + filter_units)
    existing = catalog.query(
        "SELECT dataset_digest, episodes, kept_episodes, triplets FROM iterations WHERE unit_key = ?", [key]
    )
    if existing:
        digest, episodes, kept, triplets = existing[0]
        skipped = True
    else:  # the query above was the registration check: register without a second one
        started = time.monotonic()
        selection = Selection(tuple(explore_units), tuple(filter_units))
        digest, counts = selection.digest(catalog), selection.counts(catalog)
        episodes, kept, triplets = counts["episodes"], counts["kept_episodes"], counts["triplets"]
        row = {"unit_key": key, "campaign": config.name, "iteration": iteration, "dataset_digest": digest,
               "explore_units": explore_units, "filter_units": filter_units, **counts}
        StageUnits(catalog, STAGE, config.name, iteration).register(
            key, UnitOutput({"dataset_digest": digest, **counts}, rows={"iterations": [row]}), time.monotonic() - started)
        skipped = False
    log.info(
        "index it%d: dataset %s: %d triplets from %d kept of %d episodes (iterations 0..%d)%s",
        iteration, digest[:12], triplets, kept, episodes, iteration, ", already registered" if skipped else "",
    )
    if triplets == 0:
        raise NothingToTrain(
            f"iteration {iteration}: the filter kept no episode (filter.min_return={config.filter.min_return}); "
            "nothing to train on"
        )
    return IndexResult(
        unit_key=key, iteration=iteration, dataset_digest=digest, explore_units=explore_units,
        filter_units=filter_units, episodes=episodes, kept_episodes=kept, triplets=triplets, skipped=skipped,
    )
