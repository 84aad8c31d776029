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
