"""Nothing outlives its run: a watchdog process that, when a command dies however it dies (SIGKILL
included), kills every process the command started: Prefect's temporary API server (uvicorn, ~250 MB),
the rollout workers, the DataLoader workers.

Why a watchdog and not the children's own parent-death signal: Prefect starts its server with a plain
Popen we do not control, PR_SET_PDEATHSIG fires when the *thread* that started a child ends (not the
process), and a process group cannot be used without taking the command out of its terminal's
foreground group (Ctrl-C would no longer reach it). The watchdog follows the command's process tree
instead: every `POLL_S` it records the tree's processes (pid and start time, so a reused pid is
never hit), and once the command is gone it SIGKILLs those still alive, then exits. A child started
and orphaned within one poll is the only one it can miss.

    python -m flows.lifetime <pid>      # what `watch()` starts, detached from the command's group
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import psutil

POLL_S = 0.25


def watch() -> subprocess.Popen:
    """Start the watchdog of this process; it ends by itself when this process ends. Idempotent per
    process (a command that calls it twice keeps one watchdog)."""
    if _WATCHDOG:
        return _WATCHDOG[0]
    watchdog = subprocess.Popen([sys.executable, "-m", "flows.lifetime", str(os.getpid())],
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True)  # not in the command's group: a group kill spares it
    _WATCHDOG.append(watchdog)
    return watchdog


_WATCHDOG: list[subprocess.Popen] = []


def _descendants(parent: psutil.Process) -> dict[int, float]:
    try:
        children = parent.children(recursive=True)
    except psutil.Error:
        return {}
    found = {}
    for child in children:
        try:
            if child.pid != os.getpid():
                found[child.pid] = child.create_time()
        except psutil.Error:
            pass
    return found


def _alive(process: psutil.Process) -> bool:
    try:
        return process.is_running() and process.status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def guard(pid: int) -> list[int]:
    """Follow `pid`'s process tree until `pid` ends, then SIGKILL what is left of it. -> the pids killed."""
    try:
        command = psutil.Process(pid)
    except psutil.NoSuchProcess:
        return []
    seen: dict[int, float] = {}
    while _alive(command):
        seen.update(_descendants(command))
        time.sleep(POLL_S)
    killed = []
    for child, started in seen.items():
        try:
            process = psutil.Process(child)
            if process.create_time() == started:  # the same process, not a reused pid
                process.send_signal(signal.SIGKILL)
                killed.append(child)
        except psutil.Error:
            pass
    return killed


if __name__ == "__main__":
    guard(int(sys.argv[1]))
