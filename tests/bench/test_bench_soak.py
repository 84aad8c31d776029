"""`sim2act bench soak` on the smoke campaign: its API server and then its flow SIGKILLed mid-run, the
campaign resumed each time to its end, every finished part kept as it was, the report written; and a
run whose temporary Prefect server died stops at once, naming it (it retried for ~4 minutes)."""

from __future__ import annotations

import json
import os
import subprocess

from tests.conftest import SIM2ACT


def test_a_soaked_campaign_keeps_its_finished_parts_and_a_run_ends_with_its_server(tmp_path):
    workspace = tmp_path / "workspace"
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}  # each run its own temporary server
    # each kill 12-16 s into a start: its server is up by then (~9 s, its database made), and the start after the
    # first kill still has ~20 s of iteration 0 ahead of it, so the second kill cannot miss (a third start would)
    done = subprocess.run(
        [SIM2ACT, "bench", "soak", "--preset", "smoke", "--iterations", "1", "--workspace", str(workspace),
         "--kills", "2", "--kinds", "server,flow", "--wait", "12", "16", "--out", str(tmp_path / "soak.md")],
        env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    result = json.loads((tmp_path / "soak.json").read_text())
    assert result["ended"] == "finished" and result["final_sha256_ok"] is True
    assert len(result["kills"]) == 2 and result["starts"] == 3
    # every kill ended the campaign at once: a dead server too (before, the run outlived it by minutes)
    assert all(k["campaign_ended"] and k["outlived"] == 0 for k in result["kills"]), \
        [{key: k[key] for key in ("kind", "start_to_kill_s", "campaign_ended", "outlived_what")} for k in result["kills"]]
    assert {k["kind"] for k in result["kills"]} <= {"server", "flow"}
    assert all(c["kept"] and not c["bad_files"] for c in result["checks"]), result["checks"]
    assert result["checks"][-1]["units"] > 0
    logs = "".join(p.read_text() for p in sorted((workspace / "soak").glob("run-*.log")))
    if any(k["kind"] == "server" for k in result["kills"]):
        assert "Prefect's temporary API server" in logs and "died" in logs
    assert "| kill | what |" in (tmp_path / "soak.md").read_text()


def _soak_with(monkeypatch, tmp_path, snapshots: list, kills: int):
    """bench.soak.soak with a campaign that exits 0 at once and catalog snapshots in the order given."""
    import sys

    from bench import soak as soak_module

    real_popen = subprocess.Popen
    monkeypatch.setattr(soak_module.subprocess, "Popen",
                        lambda command, **kw: real_popen([sys.executable, "-c", "pass"], **kw))
    calls = iter(snapshots)
    monkeypatch.setattr(soak_module, "_snapshot", lambda catalog: next(calls))
    return soak_module.soak(["--preset", "smoke"], tmp_path / "ws", kills, 0, (1.0, 1.0), tmp_path / "logs")


def test_a_part_lost_at_any_check_fails_the_soak_though_the_end_looks_whole(monkeypatch, tmp_path):
    """A kill tore a finished shard: the check after it saw the change, the resume made the unit again, and
    the end matched that remade state. The verdict reads every check, not the last."""
    whole, torn = ({"u1"}, {"s1": (10, "aaa")}), ({"u1"}, {"s1": (10, "bbb")})
    result = _soak_with(monkeypatch, tmp_path, [whole, torn, torn], kills=0)
    assert [c.kept for c in result.checks] == [True, False, True]
    assert result.ended == "finished" and result.final_sha256_ok is False


def test_a_campaign_that_finishes_before_its_kills_ends_the_soak_unpassed(monkeypatch, tmp_path):
    """It was started again and again for ever (each start finished at once, no kill landed)."""
    empty = (set(), {})
    result = _soak_with(monkeypatch, tmp_path, [empty] * 3, kills=2)
    assert result.starts == 1 and result.kills == []
    assert result.ended == "finished after 0 of 2 kills"
