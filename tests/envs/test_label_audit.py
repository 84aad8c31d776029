"""sim2act labels: a noisy expert's real episodes (robosuite Lift, MetaWorld reach), labelled by the
noiseless expert as they were explored, replayed state by state: the replayed labels are the stored
ones bit for bit, and the table counts the phases they came from."""

import numpy as np
import pytest

from envs.label_audit import LabelAuditError, audit_labels, markdown
from flows.cli import main
from schemas.config import CampaignConfig
from tests.explored import explored_workspace
from warehouse.catalog import Catalog

CONFIG = CampaignConfig.model_validate({
    "name": "labels",
    "tasks": {"specs": ["lift", "mw-reach"], "include": ["lift-red", "mw-reach"], "weak_experts": "keep",
              "horizon": {"lift": 70, "mw-reach": 10}},  # long enough for the expert to grasp and lift
    "explore": {"episodes_per_task": 2, "episodes_per_shard": 2},
})


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory):
    return explored_workspace(tmp_path_factory.mktemp("labels"), CONFIG)


def test_the_replayed_labels_are_the_stored_ones_and_their_phases_are_counted(workspace):
    catalog = Catalog(workspace.catalog)
    progress = []
    audit = audit_labels(catalog, 0, "expert", progress=lambda done, total: progress.append((done, total)))
    [row] = audit.tasks
    [(steps, closing)] = catalog.query(
        "SELECT count(*), count(*) FILTER (WHERE expert_action[7] > 0) FROM steps WHERE task_id = 'lift-red'")
    assert (row.task_id, row.episodes, row.steps) == ("lift-red", 2, steps)
    assert row.mismatched == 0  # every replayed label equals the stored one
    assert row.closed == closing > 0  # the expert grasped: its labels close the gripper, as stored
    assert {"approach", "grasp", "lift"} <= set(row.phases) and sum(row.phases.values()) == steps
    assert 0 < row.at_grasp <= row.near_grasp and len(row.misturn_at_grasp) == row.at_grasp
    assert audit.skipped == {"metaworld": 2}  # labelled too, but a replay cannot label them
    assert progress == [(0, 2), (1, 2), (2, 2)] and audit.campaign == "labels"
    table = markdown(audit)
    assert "| lift-red | 2 |" in table and "| **all** | 2 |" in table and "2 metaworld episode(s)" in table


@pytest.mark.parametrize("nudge, caught", [(1e-3, True), (1e-9, False)])
def test_a_replayed_label_that_differs_is_counted(workspace, monkeypatch, nudge, caught):
    """The check can fail: an expert that answers otherwise than the stored labels is caught at every step;
    one that differs by rounding noise (a restored state's) is not."""
    import envs.registry

    real = envs.registry.make_expert

    def nudged(*args):
        act = real(*args)
        return lambda obs: np.asarray(act(obs)) + nudge

    monkeypatch.setattr(envs.registry, "make_expert", nudged)
    [row] = audit_labels(Catalog(workspace.catalog), 0, "expert").tasks
    assert row.mismatched == (row.steps if caught else 0) and row.steps > 0


def test_no_labelled_episode_is_one_line(workspace):
    with pytest.raises(LabelAuditError) as refused:
        audit_labels(Catalog(workspace.catalog), 0, "policy%")
    message = str(refused.value)
    assert message.startswith("labels: expected labelled robosuite episodes of iteration 0 by an explorer like "
                              "'policy%', got none; ") and "\n" not in message
    with pytest.raises(LabelAuditError, match="^labels: expected labelled robosuite episodes of campaign 'other' of "):
        audit_labels(Catalog(workspace.catalog), 0, "expert", campaign="other")


def test_the_cli_prints_the_table_and_writes_it(workspace, tmp_path, capsys):
    out = tmp_path / "labels.md"
    assert main(["labels", "--workspace", str(workspace.root), "--iteration", "0", "--explorer", "expert",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "| lift-red | 2 |" in printed and out.read_text().strip() == printed.strip()
    assert main(["labels", "--workspace", str(workspace.root), "--iteration", "3"]) == 2
    assert capsys.readouterr().err.startswith("sim2act: labels: expected labelled robosuite episodes of iteration 3")


def test_several_campaigns_without_one_named_is_one_line(tmp_path, monkeypatch):
    found = [("alpha", "alpha-e0", "lift-red", "robosuite"), ("beta", "beta-e0", "lift-red", "robosuite")]
    monkeypatch.setattr("envs.label_audit.labelled_episodes", lambda *args: found)
    with pytest.raises(LabelAuditError) as refused:
        audit_labels(Catalog(tmp_path / "catalog.duckdb"), 2)
    assert str(refused.value) == ("labels: iteration 2 holds labelled episodes of campaigns alpha, beta; expected one "
                                  "named (--campaign)")
