"""Nothing outlives its run: a watchdog process that, when a command dies however it dies (SIGKILL
included), kills every process the command started: Prefect's temporary API server (uvicorn, ~250 MB),
the rollout workers, the DataLoader workers.

Why a watchdog and not the children's own parent-death signal: Prefect starts its server with a plain
Popen we do not control, PR_SET_PDEATHSIG fires when the *thread* that started a child ends (not the
process), and a process group cannot be used without taking the command out of its terminal's
foreground group (Ctrl-C would no longer reach it). The watchdog follows the command's process tree
instead: every `POLL_S` it records the tree's processes (pid and start time, so a reused pid is
never hit), and once the command is gone it SIGKILLs those still alive, then exits.

A child started within one poll of the command's death is not in that record (on 2 loaded cores one
poll of the tree takes longer than `POLL_S`; CI once saw a process outlive a soak's SIGKILLed run by
over 30 s), nor is anything when the command dies before its watchdog has started. So the command
also marks its environment, which every child it execs inherits (rollout workers are spawned,
Prefect's server is a Popen): `LINEAGE_ENV` lists a token per watched ancestor, and once the command
is gone the watchdog also kills every process whose environment carries its token, recorded or not.

    python -m flows.lifetime <pid> <token>   # what `watch()` starts, detached from the command's group

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
LINEAGE_ENV = "SIM2ACT_LINEAGE"  # ":"-joined tokens, one per watched ancestor (a watched command that starts another: two)
SWEEPS = 5  # scans for carriers after the command died: one started during a scan is found by the next


def watch() -> subprocess.Popen:
    """Start the watchdog of this process; it ends by itself when this process ends. Idempotent per
    process (a command that calls it twice keeps one watchdog). Marks this process's environment
    first, so every child started from now on carries the token the watchdog looks for."""
    if _WATCHDOG:
        return _WATCHDOG[0]
    token = _token(psutil.Process())
    os.environ[LINEAGE_ENV] = ":".join(filter(None, [os.environ.get(LINEAGE_ENV), token]))
    watchdog = subprocess.Popen([sys.executable, "-m", "flows.lifetime", str(os.getpid()), token],
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True)  # not in the command's group: a group kill spares it
    _WATCHDOG.append(watchdog)
    return watchdog


_WATCHDOG: list[subprocess.Popen] = []


def _token(process: psutil.Process) -> str:
    """The lineage token of `process`: its pid and start time (a reused pid gets another)."""
    return f"{process.pid}.{int(process.create_time() * 1000)}"


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


def _carrying(token: str) -> dict[int, float]:
    """Every process whose environment this one can read (not another user's unless root, nor a
    non-dumpable one) and lists `token`."""
    found = {}
    for process in psutil.process_iter():
        try:
            if process.pid != os.getpid() and token in process.environ().get(LINEAGE_ENV, "").split(":"):
                found[process.pid] = process.create_time()
        except psutil.Error:
            pass
    return found


def guard(pid: int, token: str | None = None) -> list[int]:
    """Follow `pid`'s process tree until `pid` ends, then SIGKILL what is left of it, and every process
    whose environment carries `token` (a child too young for the last poll). -> the pids killed."""
    seen: dict[int, float] = {}
    try:
        command = psutil.Process(pid)
        if token and _token(command) != token:  # gone before this watchdog started, its pid reused
            raise psutil.NoSuchProcess(pid)
    except psutil.NoSuchProcess:  # gone before this watchdog started: its lineage is all there is to go by
        command = None
    while command is not None and _alive(command):
        seen.update(_descendants(command))
        time.sleep(POLL_S)
    killed = _kill(seen)  # the recorded tree first: no scan stands between its death and theirs
    for _ in range(SWEEPS if token else 0):  # then the carriers, until a scan finds none alive
        found = {pid: started for pid, started in _carrying(token).items() if pid not in killed}
        if not found:
            break
        killed += _kill(found)
    return killed


def _kill(processes: dict[int, float]) -> list[int]:
    """SIGKILL each (pid, start time) still running as that same process (not a reused pid). -> the pids killed."""
    killed = []
    for child, started in processes.items():
        try:
            process = psutil.Process(child)
            if process.create_time() == started:
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
    guard(int(sys.argv[1]), sys.argv[2] if len(sys.argv) > 2 else None)
