"""The DataLoader a training reads through, in a process that has run a Prefect flow (as `sim2act run`'s
training does): a forked worker of such a process exits with code 1 (Prefect's thread-exit hook asserts
on state its after-fork reset cleared), which the DataLoader takes for a crash when the epoch ends."""

from __future__ import annotations

import pytest
from prefect import flow
from prefect.settings import PREFECT_API_URL, temporary_settings

from bench.synthetic import register_explore_unit
from schemas.workspace import Workspace
from warehouse.catalog import Catalog
from warehouse.training_reader import StepBatches, select_rows, training_loader


def _selected_rows(tmp_path):
    """The steps of a small synthetic warehouse (two explore units), selected as a training selects them."""
    workspace = Workspace.at(tmp_path / "ws").create()
    Catalog(workspace.catalog).initialise()
    for u in range(2):
        register_explore_unit(workspace, f"explore-{u}", seed=u, steps=20, unique_frames=4)
    return select_rows(Catalog(workspace.catalog), "NOT done")


@flow(name="a-flow-before-the-loader")
def a_flow() -> int:
    return 1


def test_every_row_comes_through_spawned_workers_after_a_flow_ran_here(prefect_api, tmp_path):
    with temporary_settings({PREFECT_API_URL: prefect_api}):
        assert a_flow() == 1
    batches = StepBatches(_selected_rows(tmp_path), batch_size=16, shuffle_buffer=32, seed=0, epochs=2, workers=2)
    assert sum(len(batch["action"]) for batch in training_loader(batches, workers=2)) == 2 * batches.rows_per_epoch


def test_the_workers_must_be_those_the_batches_were_split_for(tmp_path):
    batches = StepBatches(_selected_rows(tmp_path), batch_size=16, shuffle_buffer=32, seed=0, epochs=1, workers=2)
    with pytest.raises(ValueError, match="expected the 2 worker"):
        training_loader(batches, workers=3)


def test_starting_a_loader_leaves_torchs_global_generator_alone(tmp_path):
    """A resumed training starts one more loader than a straight one: drawing its workers' base seed from torch's
    global generator put every later global draw (a trainable MiniLM's dropout) one ahead after a resume."""
    import torch

    batches = StepBatches(_selected_rows(tmp_path), batch_size=16, shuffle_buffer=32, seed=0, epochs=1, workers=0)
    torch.manual_seed(5)
    before = torch.get_rng_state()
    rows = sum(len(batch["action"]) for batch in training_loader(batches, workers=0))
    assert rows == batches.rows_per_epoch and torch.equal(torch.get_rng_state(), before)
