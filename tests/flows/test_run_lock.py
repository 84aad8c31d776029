"""Two runs on one workspace: the second is refused in one line naming the first, and writes
nothing; the lock goes with its holder, however it ends."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest

from flows.run_lock import WorkspaceBusy, exclusive_run, run_holder
from schemas.workspace import Workspace
from tests.conftest import SIM2ACT, sim2act_env


def test_a_second_run_on_a_busy_workspace_is_refused_and_writes_nothing(tmp_path, prefect_api):
    workspace = Workspace.at(tmp_path / "workspace")
    with exclusive_run(workspace, "first"):
        second = subprocess.run([SIM2ACT, "run", "--preset", "smoke", "--workspace", str(workspace.root)],
                                env=sim2act_env(prefect_api), capture_output=True, text=True, timeout=300)
        assert second.returncode == 2, second.stdout[-2000:] + second.stderr[-2000:]
        [line] = [line for line in second.stderr.splitlines() if line.startswith("sim2act:")]
        assert f"workspace {workspace.root} is in use by another run" in line
        holder = json.loads(line[line.index("{"):line.index("}") + 1])
        assert holder["campaign"] == "first" and holder["pid"] == os.getpid()
        assert not workspace.catalog.exists() and not any(workspace.shards.rglob("*.parquet"))
        with pytest.raises(WorkspaceBusy):  # the same holds within one process
            with exclusive_run(workspace, "again"):
                pass
    with exclusive_run(workspace, "after"):  # released on exit
        assert json.loads(workspace.run_lock.read_text())["campaign"] == "after"


def test_a_run_told_to_wait_takes_the_workspace_when_the_holder_lets_go(tmp_path, monkeypatch):
    """What a scheduled run does behind a `sim2act run` from the CLI (the CLI's own second run is refused)."""
    import threading

    monkeypatch.setattr("flows.run_lock.LOCK_POLL_S", 0.05)
    workspace = Workspace.at(tmp_path / "workspace")
    held, told = threading.Event(), []

    def hold() -> None:
        with exclusive_run(workspace, "first"):
            held.set()
            time.sleep(0.5)

    thread = threading.Thread(target=hold)
    thread.start()
    held.wait(10)
    with pytest.raises(WorkspaceBusy, match=r"\(waited 0 s\)"):  # a wait shorter than the hold
        with exclusive_run(workspace, "impatient", wait_s=0.1):
            pass
    with exclusive_run(workspace, "nightly", wait_s=30, on_wait=told.append):
        assert json.loads(workspace.run_lock.read_text())["campaign"] == "nightly"
    thread.join()
    assert len(told) == 1 and json.loads(told[0])["campaign"] == "first"


def test_a_killed_holder_leaves_the_workspace_free(tmp_path):
    """... and `run_holder` (what `sim2act report` says of the trainings it lists) names the holder while it lives,
    none once it is killed (its words stay in the file) or has let go (the file emptied)."""
    workspace = Workspace.at(tmp_path / "workspace")
    assert run_holder(workspace) is None  # never run here
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom flows.run_lock import exclusive_run\n"
         "from schemas.workspace import Workspace\n"
         f"with exclusive_run(Workspace.at({str(workspace.root)!r}), 'held'):\n"
         "    print('held', flush=True); time.sleep(600)"],
        stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    with pytest.raises(WorkspaceBusy, match="held"):
        with exclusive_run(workspace, "second"):
            pass
    assert run_holder(workspace)["campaign"] == "held" and run_holder(workspace)["pid"] == holder.pid
    holder.kill()
    holder.wait()
    assert json.loads(workspace.run_lock.read_text())["campaign"] == "held" and run_holder(workspace) is None
    with exclusive_run(workspace, "second"):
        assert run_holder(workspace)["pid"] == os.getpid()
    assert run_holder(workspace) is None


def test_run_holder_takes_the_lock_not_the_words_on_this_host(tmp_path):
    """A lock file's words without the lock (a killed run whose PID a later process reuses: here this very process)
    name no holder; a holder on another host (a shared folder) is taken at its word; a file that is not a run's
    words is none."""
    import socket
    import time

    workspace = Workspace.at(tmp_path / "workspace")
    workspace.root.mkdir(parents=True)
    words = {"campaign": "gone", "pid": os.getpid(), "host": socket.gethostname(), "since": "", "started": time.time()}
    workspace.run_lock.write_text(json.dumps(words))
    assert os.path.exists("/proc/locks") and run_holder(workspace) is None  # the PID is alive; nothing holds the lock
    workspace.run_lock.write_text(json.dumps({**words, "host": "elsewhere"}))
    assert run_holder(workspace)["host"] == "elsewhere"
    for junk in ("[1]", '{"campaign": "x"}', '{"pid": "12", "host": "elsewhere"}', '{"pid": 0, "host": "elsewhere"}',
                 '{"pid": -1, "host": "elsewhere"}', '{"pid": 1', ""):
        workspace.run_lock.write_text(junk)
        assert run_holder(workspace) is None, junk
