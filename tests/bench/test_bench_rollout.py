"""`sim2act bench rollout` runs the plain robosuite loops and the explore stage side by side."""

import json
import os

import pytest

from envs.robosuite_control import STOCK_CONTROL
from flows.cli import main


def test_bench_rollout_reports_every_case_and_the_ratios_between_them(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("SIM2ACT_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "docs" / "bench-rollout.md"
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    assert main(["bench", "rollout", "--quick", "--json", "--scratch", str(scratch), "--out", str(out)]) == 0
    bench = json.loads(capsys.readouterr().out)
    assert bench["env"] == "Lift" and bench["image_size"] == 84 and bench["policy"] == "scripted expert"
    rows = {r["case"]: r for r in bench["rows"]}
    assert list(rows) == ["a", "b", "c1", "c2", "d"]
    assert [rows[c]["workers"] for c in rows] == [1, 1, 1, 2, 1]
    # fewer triangles, the same physics: the same episodes end the same way
    assert (rows["d"]["steps"], rows["d"]["successes"]) == (rows["c1"]["steps"], rows["c1"]["successes"])
    for row in rows.values():
        assert row["episodes"] == bench["episodes"] == 2  # the same episodes in every case
        assert 0 < row["steps"] <= bench["episodes"] * bench["horizon"]
        assert row["wall_s"] > 0 and row["cpu_s"] > 0
        assert row["steps_per_s"] == pytest.approx(row["steps"] / row["wall_s"])
        assert row["steps_per_s_per_core"] == pytest.approx(row["steps_per_s"] / row["workers"])
    ratios = {r["name"]: r for r in bench["ratios"]}
    versus_plain = ratios["(c, 1 worker) / (a), per core"]
    assert versus_plain["value"] == pytest.approx(rows["c1"]["steps_per_s"] / rows["a"]["steps_per_s"])
    assert versus_plain["target"] == 2.0 and versus_plain["met"] == (versus_plain["value"] >= 2.0)
    scaling = ratios["(c, 2 workers) / (c, 1 worker)"]
    assert scaling["value"] == pytest.approx(rows["c2"]["steps_per_s"] / rows["c1"]["steps_per_s"])
    assert scaling["target"] == 1.8 and scaling["met"] == (scaling["value"] >= 1.8)
    meshes = ratios["(d) / (c, 1 worker)"]
    assert meshes["value"] == pytest.approx(rows["d"]["steps_per_s"] / rows["c1"]["steps_per_s"])
    table = out.read_text()
    assert "`sim2act bench rollout --quick --json" in table
    assert all(f"\n| {case} | " in table for case in rows) and "(c, 2 workers) / (c, 1 worker)" in table
    assert list(scratch.iterdir()) == []  # the throwaway workspaces are gone


def test_bench_rollout_mix_explores_the_same_episodes_on_every_side(tmp_path, capsys, monkeypatch):
    """--mix: the stage over a sample of the generalist's tasks, as it was, with decimated meshes, with the
    fused substeps too, and with the colliding meshes decimated as well, per family, cold and then warm on
    the same worker."""
    monkeypatch.setenv("SIM2ACT_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv(STOCK_CONTROL, raising=False)
    out = tmp_path / "mix.md"
    assert main(["bench", "rollout", "--mix", "--quick", "--json", "--scratch", str(tmp_path), "--out", str(out)]) == 0
    bench = json.loads(capsys.readouterr().out)
    assert bench["tasks"] == ["mw-assembly", "nav-room-red", "lift-red"]  # each family's first spec with a seen task
    assert [(s["mesh_detail"], s["fused_control"], s["decimate_colliding"]) for s in bench["sides"]] == [
        (1.0, False, False), (0.1, False, False), (0.1, True, False), (0.1, True, True)]
    families = {f["family"]: f for f in bench["families"]}
    assert sorted(families) == ["metaworld", "navigation", "robosuite"]
    for family in families.values():  # the same steps on every side is checked by the bench itself
        assert family["tasks"] == family["episodes"] == 1 and family["steps"] > 0
        assert len(family["seconds"]) == len(family["warm_seconds"]) == 4
        assert min(family["seconds"]) > 0 and min(family["warm_seconds"]) > 0
    # cold, each unit made its environment; warm, the same worker had it: robosuite's ~2 s scene build
    robosuite = families["robosuite"]
    assert all(cold > warm + 0.5 for cold, warm in zip(robosuite["seconds"], robosuite["warm_seconds"]))
    # the preset's mix: each family's seconds per step weighted by the steps the preset explores in it
    shares = bench["preset_steps"]
    assert sorted(shares) == sorted(families) and shares["robosuite"] > shares["navigation"] > 0
    table = out.read_text()
    assert table.count("| all | 3 | 3 |") == 2
    for phase in ("warm_seconds", "seconds"):  # the warm table first
        weighted = [sum(n * families[f][phase][side] / families[f]["steps"] for f, n in shares.items())
                    / sum(shares.values()) for side in range(4)]
        ratios = " | ".join(f"**{weighted[0] / weighted[side]:.2f}×**" for side in (1, 2, 3)) + " |"
        assert ratios in table
        table = table[table.index(ratios) + len(ratios):]
    assert os.environ.get(STOCK_CONTROL) is None  # the bench leaves the variable as it found it


def test_bench_rollout_mix_refuses_a_callers_kept_pool():
    """Inside keep_workers every side would borrow one worker, spawned with the first side's
    controller path and warm after it: the bench says so before any work."""
    from bench.rollout_mix import QUICK, bench_mix
    from envs.pool import keep_workers

    with keep_workers(), pytest.raises(RuntimeError, match="fresh worker per side"):
        bench_mix(QUICK)
