"""The disk a campaign's exploration needs, estimated before any work (warehouse/capacity.py), and the
generalist preset it exists for (issue 11), checked at the size of its config, not its million."""

from __future__ import annotations

import collections
import shutil

import pytest

from envs.suite import generate_tasks, weak_tasks_left_out
from schemas.config import load_config
from schemas.experts import TARGET, load_expert_table
from schemas.workspace import Workspace
from stages.adapt import adapted_tasks
from warehouse import capacity
from warehouse.capacity import BYTES_PER_STEP_84PX, InsufficientDisk, check_disk, explore_estimate


def test_the_generalist_preset_spans_the_three_families_with_capable_experts_and_a_million_steps():
    config = load_config("generalist")
    tasks = generate_tasks(config.tasks, config.seed)
    by_family = collections.Counter(t.family for t in tasks)
    assert len(tasks) >= 100 and set(by_family) == {"robosuite", "metaworld", "navigation"}, by_family
    assert {t.family for t in tasks if t.split == "unseen"} == set(by_family)  # held-out tasks in every family
    experts = load_expert_table()
    assert all(experts.rows[t.task_id].success_rate >= TARGET for t in tasks)  # every one measured, all >= 90%
    assert {t.spec for t in tasks} >= {"nav-room-sequence", "nut-square", "mw-assembly"}  # long-horizon specs too
    estimate = explore_estimate(config, tasks)
    # kept: each seen task's explored steps weighted by its expert's success (the filter keeps successes)
    kept = sum(config.explore.episodes_per_task * experts.rows[t.task_id].mean_length * experts.rows[t.task_id].success_rate
               for t in tasks if t.split == "seen")
    assert estimate.iterations == 1 and kept >= 1_000_000
    assert 3e9 < estimate.bytes < 5e9  # ~2.9 KB a step at 84 px, +20%
    adapted = adapted_tasks(config, tasks)  # its adaptation's tasks are seen tasks of all three families
    assert {t.family for t in adapted} == set(by_family) and len(adapted) == len(config.adapt.tasks)


def test_tasks_left_out_for_a_weak_expert_are_named():
    config = load_config("smoke", overrides={"tasks": {"specs": ["nut-square", "lift"], "colours": ["red", "yellow"]}})
    assert weak_tasks_left_out(config.tasks) == ["nut-square-yellow"]
    assert "nut-square-yellow" not in {t.task_id for t in generate_tasks(config.tasks, config.seed)}
    keep = load_config("smoke", overrides={"tasks": {"specs": ["nut-square"], "weak_experts": "keep"}})
    assert weak_tasks_left_out(keep.tasks) == []


def test_bytes_per_step_come_from_the_warehouse_once_it_has_steps(tmp_path):
    from tests.warehouse.filled import fill  # a warehouse with real steps shards
    from warehouse.catalog import Catalog

    config = load_config("smoke")
    tasks = generate_tasks(config.tasks, config.seed)
    fresh = explore_estimate(config, tasks)
    assert fresh.bytes_per_step == BYTES_PER_STEP_84PX and not fresh.measured_here
    big = explore_estimate(load_config("smoke", overrides={"render": {"image_size": 168}}), tasks)
    assert big.bytes_per_step == 4 * BYTES_PER_STEP_84PX and big.steps == fresh.steps
    workspace = Workspace.at(tmp_path).create()
    fill(workspace)
    catalog = Catalog(workspace.catalog)
    [(size, rows)] = catalog.query("SELECT sum(num_bytes), sum(num_rows) FROM shards WHERE table_name = 'steps'")
    assert not explore_estimate(config, tasks, catalog).measured_here  # another campaign's frames ('bench') do not count
    measured = explore_estimate(config.model_copy(update={"name": "bench"}), tasks, catalog)
    assert measured.measured_here and measured.bytes_per_step == pytest.approx(size / rows)


def test_a_campaign_the_disk_cannot_hold_is_one_line_before_anything_is_written(tmp_path, monkeypatch, capsys):
    from flows.cli import main

    free = shutil.disk_usage(tmp_path).free
    config = load_config("generalist")
    tasks = generate_tasks(config.tasks, config.seed)
    assert check_disk(tmp_path / "not-yet", load_config("smoke"), generate_tasks(load_config("smoke").tasks, 0)).steps > 0
    monkeypatch.setattr(capacity.shutil, "disk_usage", lambda path: shutil._ntuple_diskusage(free, free - 10**9, 10**9))
    with pytest.raises(InsufficientDisk, match=r"needs about 3\.\d GB for 1 more iteration\(s\) \(1,08\d,\d{3} steps x "
                                               r"2\.9 KB at 84 px, \+20%\), but .* has 1\.0 GB free"):
        check_disk(tmp_path, config, tasks)
    workspace = tmp_path / "ws"
    assert main(["run", "--preset", "generalist", "--workspace", str(workspace)]) == 2
    [line] = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("sim2act: explore: campaign 'generalist' needs about") and "lower explore.episodes_per_task" in line
    assert not workspace.exists()
