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

The other way round, a run does not outlive its temporary API server (`ends_with_its_server`): once
Prefect's embedded server dies, the run can no longer record its flow's state, and Prefect's client
retried that for ~4 minutes before the command exited (measured by `sim2act bench soak`). The run
stops at once instead, with one line, losing at most the units in flight; `sim2act run` resumes it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

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


SERVER_POLL_S = 1.0
SERVER_DIED_EXIT = 75  # EX_TEMPFAIL: try again (the run resumes)


def _temporary_server() -> psutil.Process | None:
    """Prefect's embedded API server, a uvicorn child of this process; None while it has none."""
    for child in psutil.Process().children():
        try:
            cmdline = child.cmdline()
        except psutil.Error:
            continue
        if "uvicorn" in " ".join(cmdline) and any("prefect.server.api.server" in part for part in cmdline):
            return child
    return None


@contextmanager
def ends_with_its_server(resume_hint: str) -> Iterator[None]:
    """While the block runs, a thread follows this process's temporary Prefect server: once one has
    been seen and is gone, print one line (what died, how to resume) and end this process at once
    (`os._exit`: Prefect's own retries are what would hang). A run against a server it did not start
    (PREFECT_API_URL) has none to follow, and waits for that server as Prefect's client does."""
    if os.environ.get("PREFECT_API_URL"):  # a server it did not start: nothing of its own to follow
        yield
        return
    done = threading.Event()

    def follow() -> None:
        server = None
        while not done.wait(SERVER_POLL_S):
            if server is None:
                server = _temporary_server()
            elif not _alive(server) and not done.is_set():
                try:
                    code = server.wait(timeout=0)
                except psutil.Error:
                    code = None
                print(f"sim2act: Prefect's temporary API server (pid {server.pid}) died (exit {code}); this run can "
                      f"no longer record its state, so it stops here. Finished units are kept: {resume_hint}",
                      file=sys.stderr, flush=True)
                os._exit(SERVER_DIED_EXIT)

    thread = threading.Thread(target=follow, name="sim2act-server-watch", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()  # Prefect stops its server after the run: that is no death
        thread.join()


if __name__ == "__main__":
    guard(int(sys.argv[1]))
