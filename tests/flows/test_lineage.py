"""The watchdog's second net (flows/lifetime.py): processes that carry a run's lineage token in their
environment die with the run, even those its record of the run's tree never saw; processes without
the token live on, and the stack `sim2act up` starts carries none."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil

from flows.lifetime import LINEAGE_ENV, guard
from flows.service import stack
from schemas.service import ServiceConfig
from schemas.workspace import Workspace

ROOT = Path(__file__).parents[2]


def alive(pid: int, created: float) -> bool:
    """The process `pid` started at `created` still runs (a zombie does not)."""
    try:
        process = psutil.Process(pid)
        return process.create_time() == created and process.status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def _gone_within(process: psutil.Process, created: float, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while alive(process.pid, created) and time.monotonic() < deadline:
        time.sleep(0.1)
    return not alive(process.pid, created)


def test_a_child_orphaned_before_the_watchdog_saw_it_is_killed_by_its_lineage(tmp_path):
    """A grandchild whose parent exits at once is reparented before any poll of the tree can see it
    (a child started just before the run's SIGKILL is the same case); the lineage token still names it."""
    orphan_pid = tmp_path / "orphan.pid"
    script = ("import subprocess, sys, time\n"
              "from flows.lifetime import watch\n"
              "watch()\n"
              f"subprocess.run(['sh', '-c', 'sleep 600 & echo $! > {orphan_pid}'], check=True)\n"
              "print('ready', flush=True)\n"
              "time.sleep(600)\n")
    command = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True,
                               env={**os.environ, "PYTHONPATH": str(ROOT)})
    orphan = None
    try:
        assert command.stdout.readline().strip() == "ready"
        orphan = psutil.Process(int(orphan_pid.read_text()))
        created = orphan.create_time()
        # not in the command's tree: only the lineage can find it
        assert orphan.pid not in {c.pid for c in psutil.Process(command.pid).children(recursive=True)}
        command.send_signal(signal.SIGKILL)
        command.wait(timeout=10)
        assert _gone_within(orphan, created, 10), "the orphaned grandchild outlived its run"
    finally:
        if command.poll() is None:
            command.kill()
        if orphan is not None and orphan.is_running():
            orphan.kill()


def test_a_run_gone_before_its_watchdog_started_still_takes_its_carriers_and_no_one_else():
    gone = subprocess.Popen(["true"])
    gone.wait()
    carrier = subprocess.Popen(["sleep", "600"], env={**os.environ, LINEAGE_ENV: f"other.1:{gone.pid}.7"})
    bystander = subprocess.Popen(["sleep", "600"], env={**os.environ, LINEAGE_ENV: "other.1"})
    try:
        watched = [psutil.Process(p.pid) for p in (carrier, bystander)]
        created = [p.create_time() for p in watched]
        time.sleep(0.2)  # both exec'd: their environments are sleep's, not the fork's copy
        assert guard(gone.pid, f"{gone.pid}.7") == [carrier.pid]
        carrier.wait(timeout=10)
        assert not alive(carrier.pid, created[0]) and alive(bystander.pid, created[1])
    finally:
        for process in (carrier, bystander):
            if process.poll() is None:
                process.kill()


def test_the_stack_carries_no_lineage(tmp_path, monkeypatch):
    """`sim2act up` from inside a watched command: its servers outlive that command, by design."""
    monkeypatch.setenv(LINEAGE_ENV, "123.456")
    specs = stack(Workspace.at(tmp_path), ServiceConfig())
    assert specs and all(LINEAGE_ENV not in spec.env for spec in specs)
