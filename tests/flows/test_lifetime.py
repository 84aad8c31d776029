"""Nothing outlives its run: SIGKILL `sim2act run` alone (not its group) mid-explore, and within a few
seconds none of the processes it started is alive: its temporary Prefect server, its rollout workers."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil

from tests.conftest import SIM2ACT


def test_after_a_sigkill_of_the_run_none_of_its_processes_is_left(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}  # its own temporary Prefect server
    run = subprocess.Popen([SIM2ACT, "run", "--preset", "smoke", "--workspace", str(tmp_path / "workspace")],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    command = psutil.Process(run.pid)
    started: dict[int, tuple[float, str]] = {}
    try:
        for line in run.stdout:
            for child in command.children(recursive=True):
                try:
                    started[child.pid] = (child.create_time(), " ".join(child.cmdline()))
                except psutil.Error:
                    pass
            if "explore it0:" in line and any("sim2act-worker" in c or "multiprocessing" in c
                                              for _, c in started.values()):
                break
        else:
            raise AssertionError("the run ended before exploring")
        assert any("uvicorn" in c for _, c in started.values()), started  # the temporary Prefect server
        run.send_signal(signal.SIGKILL)  # the command alone: its children are orphaned, as by the OOM killer
        run.wait(timeout=10)
        deadline = time.monotonic() + 10
        left = started
        while left and time.monotonic() < deadline:
            time.sleep(0.2)
            left = {pid: c for pid, (t, c) in started.items() if _alive(pid, t)}
        assert not left, f"still running after the run was killed: {left}"
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGKILL)


def _alive(pid: int, created: float) -> bool:
    try:
        process = psutil.Process(pid)
        return process.create_time() == created and process.status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def test_a_child_orphaned_before_the_watchdog_saw_it_is_killed_by_its_lineage(tmp_path):
    """A grandchild whose parent exits at once is reparented before any poll of the tree can see it
    (the race CI hit: a rollout worker started just before the run's SIGKILL); the environment's
    lineage token still names it."""
    orphan_pid = tmp_path / "orphan.pid"
    script = ("import subprocess, sys, time\n"
              "from flows.lifetime import watch\n"
              "watch()\n"
              f"subprocess.run(['sh', '-c', 'sleep 600 & echo $! > {orphan_pid}'], check=True)\n"
              "print('ready', flush=True)\n"
              "time.sleep(600)\n")
    command = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True,
                               env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[2])})
    orphan = None
    try:
        assert command.stdout.readline().strip() == "ready"
        orphan = psutil.Process(int(orphan_pid.read_text()))
        assert orphan.ppid() != command.pid  # not in the command's tree: only the lineage can find it
        created = orphan.create_time()
        command.send_signal(signal.SIGKILL)
        command.wait(timeout=10)
        deadline = time.monotonic() + 10
        while _alive(orphan.pid, created) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _alive(orphan.pid, created), "the orphaned grandchild outlived its run"
    finally:
        if command.poll() is None:
            command.kill()
        if orphan is not None and orphan.is_running():
            orphan.kill()
