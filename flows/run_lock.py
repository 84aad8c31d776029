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
from collections.abc import Iterator
from contextlib import contextmanager

from schemas.errors import Sim2ActError
from schemas.workspace import Workspace


class WorkspaceBusy(Sim2ActError, RuntimeError):
    pass


@contextmanager
def exclusive_run(workspace: Workspace, campaign: str) -> Iterator[None]:
    workspace.root.mkdir(parents=True, exist_ok=True)
    with workspace.run_lock.open("a+") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "{}"
            raise WorkspaceBusy(f"workspace {workspace.root} is in use by another run ({holder}); wait for it to "
                                "end or stop it, then run again (finished units are kept)") from None
        handle.seek(0)
        handle.truncate()
        handle.write(json.dumps({"campaign": campaign, "pid": os.getpid(), "host": socket.gethostname(),
                                 "since": time.strftime("%Y-%m-%d %H:%M:%S")}))
        handle.flush()
        try:
            yield
        finally:
            handle.truncate(0)
            fcntl.flock(handle, fcntl.LOCK_UN)


def run_holder(workspace: Workspace) -> dict | None:
    """The run holding the workspace now, as it wrote itself into the lock ({campaign, pid, host,
    since}); None when none does. Read, not locked, so that a report never stands in a run's way:
    a release empties the file, and a killed holder's words stay behind, so a holder on this host
    must also be alive (one on another host is taken at its word)."""
    try:
        holder = json.loads(workspace.run_lock.read_text() or "null")
    except (FileNotFoundError, json.JSONDecodeError):  # never run here, or caught mid-write
        return None
    if not holder or holder.get("host") != socket.gethostname():
        return holder or None
    try:
        os.kill(holder["pid"], 0)
    except ProcessLookupError:
        return None
    except PermissionError:  # alive, another user's
        pass
    return holder
