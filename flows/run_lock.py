"""One campaign at a time per workspace: a second run is refused, in one line naming the first.

An advisory `flock` on `<workspace>/run.lock`, held for the whole flow run: the kernel drops it
when the holder exits, however it exits, so a killed run never leaves the workspace locked.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from schemas.errors import Sim2ActError
from schemas.workspace import Workspace


LOCK_POLL_S = 5.0  # how often a waiting run tries the lock again


class WorkspaceBusy(Sim2ActError, RuntimeError):
    pass


@contextmanager
def exclusive_run(workspace: Workspace, campaign: str, wait_s: float = 0.0,
                  on_wait: Callable[[str], None] = lambda holder: None) -> Iterator[None]:
    """Hold the workspace for one run. `wait_s`: how long to wait for another run to let go (a scheduled
    run behind a `sim2act run` from the CLI waits; the CLI is refused at once), `on_wait` told once
    whom it waits for.

    Raises:
        WorkspaceBusy: another run holds the workspace (still, after `wait_s`)."""
    workspace.root.mkdir(parents=True, exist_ok=True)
    with workspace.run_lock.open("a+") as handle:
        deadline, told = time.monotonic() + wait_s, False
        while True:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                handle.seek(0)
                holder = handle.read().strip() or "{}"
                if time.monotonic() >= deadline:
                    waited = f" (waited {wait_s:.0f} s)" if wait_s else ""
                    raise WorkspaceBusy(f"workspace {workspace.root} is in use by another run ({holder}){waited}; "
                                        "wait for it to end or stop it, then run again (finished units are kept)") from None
                if not told:
                    on_wait(holder)
                    told = True
                time.sleep(min(LOCK_POLL_S, max(0.0, deadline - time.monotonic())))
        handle.seek(0)
        handle.truncate()
        handle.write(json.dumps({"campaign": campaign, "pid": os.getpid(), "host": socket.gethostname(),
                                 "since": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
                                 "started": time.time()}))
        handle.flush()
        try:
            yield
        finally:
            handle.truncate(0)
            fcntl.flock(handle, fcntl.LOCK_UN)


@contextmanager
def reading_shard_files(workspace: Workspace, command: str) -> Iterator[None]:
    """Held while `command` reads the warehouse's shard files at length (`sim2act train` outside a
    campaign, `export lerobot`, `warehouse verify`): beside each other and beside a campaign, but not
    beside `warehouse compact`, which deletes the files it rewrote (a training listed them once, an
    export or a verify too, and would find them gone), so whichever comes second is refused in one line.

    Raises:
        WorkspaceBusy: a compaction holds the workspace's shard files."""
    with _flock(workspace, fcntl.LOCK_SH, f"{command}: a `sim2act warehouse compact` is rewriting the shard files of "
                f"{workspace.root}; run it again when that ends"):
        yield


@contextmanager
def rewriting_shard_files(workspace: Workspace) -> Iterator[None]:
    """Held by `warehouse compact` (beside `exclusive_run`, which keeps the campaigns out).

    Raises:
        WorkspaceBusy: a command reads the shard files (`reading_shard_files`)."""
    with _flock(workspace, fcntl.LOCK_EX, f"warehouse compact: a training, export or verify is reading the shard "
                f"files of {workspace.root}; run it again when that ends (nothing was compacted)"):
        yield


@contextmanager
def _flock(workspace: Workspace, kind: int, busy: str) -> Iterator[None]:
    with workspace.shard_files_lock.open("a+") as handle:  # readable too: NFS takes a shared flock as a read lock
        try:
            fcntl.flock(handle, kind | fcntl.LOCK_NB)
        except BlockingIOError:
            raise WorkspaceBusy(busy) from None
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def run_holder(workspace: Workspace) -> dict | None:
    """The run holding the workspace now, as it wrote itself into the lock ({campaign, pid, host,
    since, started}); None when none does. Read, never locked, so that a report never stands in a
    run's way. A release empties the file but a killed holder's words stay behind, so on this host
    the lock itself must be held (Linux's /proc/locks; elsewhere, the holder's process alive); a
    holder on another host (a shared folder) is taken at its word."""
    try:
        holder = json.loads(workspace.run_lock.read_text() or "null")
    except (FileNotFoundError, json.JSONDecodeError):  # never run here, or caught mid-write
        return None
    if not isinstance(holder, dict) or not isinstance(holder.get("pid"), int) or holder["pid"] <= 0:
        return None  # released, or not a run's words
    if holder.get("host") != socket.gethostname():
        return holder
    held = _flock_held(workspace.run_lock, holder["pid"])
    if held is None:  # no /proc/locks: the holder's process alive or not
        from flows.service import is_alive  # the stack's module: not on every run's import path

        held = is_alive(holder["pid"])
    return holder if held else None


def _flock_held(path: Path, pid: int) -> bool | None:
    """Whether process `pid` holds a flock on `path`, as /proc/locks lists them; None where there is
    no /proc/locks (a PID alone can be another process's after a restart). Matched on the PID and the
    inode: the device /proc/locks prints is the superblock's, which stat() does not give on btrfs
    subvolumes or an overlay over several filesystems."""
    proc_locks = Path("/proc/locks")
    if not proc_locks.exists():
        return None
    try:
        inode = str(os.stat(path).st_ino)
    except FileNotFoundError:  # no lock file: nothing holds it
        return False
    for line in proc_locks.read_text().splitlines():  # "1: FLOCK  ADVISORY  WRITE 30368 fe:00:5603613 0 EOF"
        fields = line.replace("->", "").split()  # a waiter's line has "->"
        if len(fields) > 5 and fields[1] == "FLOCK" and fields[4] == str(pid) and fields[5].rsplit(":", 1)[-1] == inode:
            return True
    return False

