"""Nothing outlives its run: SIGKILL `sim2act run` alone (not its group) mid-explore, and within a few
seconds none of the processes it started is alive: its temporary Prefect server, its rollout workers."""

from __future__ import annotations

import os
import signal
import subprocess
import time

import psutil

from tests.conftest import SIM2ACT
from tests.flows.test_lineage import alive


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
            left = {pid: c for pid, (t, c) in started.items() if alive(pid, t)}
        assert not left, f"still running after the run was killed: {left}"
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGKILL)

