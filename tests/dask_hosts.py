"""Rollout "hosts" on one machine for the scale-out drills: a Dask scheduler on a free loopback port and
one `dask worker` per host (and, given a work pool, a Prefect worker polling the host's own work
queue), each in its own working folder with its own HOME (none of them a workspace), started as
docs/scale-out.md says (`--nthreads 1 --no-nanny`), SIGKILLed afterwards."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from tests.conftest import _free_port


@dataclass
class DaskHosts:
    address: str  # tcp://127.0.0.1:<port>, the scheduler
    root: Path  # the drill's folder: the scheduler's log, a folder per host
    roots: dict[str, Path]  # host name -> its working folder
    processes: dict[str, subprocess.Popen]  # "scheduler", each host's Dask worker, "<host>/prefect" its Prefect worker

    def kill(self, host: str) -> None:
        """The host is gone: SIGKILL its workers' whole process groups."""
        for name in (host, f"{host}/prefect"):
            if name in self.processes:
                os.killpg(self.processes[name].pid, signal.SIGKILL)
                self.processes[name].wait()

    def address_of(self, client, host: str) -> str:
        """The scheduler's address of `host`'s worker."""
        workers = {info["name"]: address for address, info in client.scheduler_info()["workers"].items()}
        assert host in workers, f"expected {host} among the scheduler's workers, got {sorted(workers)}"
        return workers[host]

    def dropped(self, address: str, killed_at: float, timeout: float = 30) -> str:
        """When the scheduler dropped the worker at `address` (its "Remove worker" line), in seconds from
        `killed_at` (time.time() at the kill: its closed connections say so at once); past `timeout` from the kill,
        that it had not, and the connections still open on the worker's port (pid, state)."""
        removed = re.compile(rf"^(\S+ \S+) - distributed\.scheduler - INFO - Remove worker addr: {re.escape(address)} ",
                             re.MULTILINE)
        while not (found := removed.search((self.root / "scheduler.log").read_text())):
            if time.time() - killed_at > timeout:
                import psutil

                port = int(address.rsplit(":", 1)[1])
                held = sorted({(c.pid, c.status) for c in psutil.net_connections("tcp")
                               if port in (c.laddr.port if c.laddr else None, c.raddr.port if c.raddr else None)},
                              key=str)
                return f"not dropped by the scheduler {timeout:.0f} s after its kill; connections on its port: {held}"
            time.sleep(0.2)
        at = datetime.strptime(found[1], "%Y-%m-%d %H:%M:%S,%f").timestamp()  # the scheduler's local time, as ours
        return f"dropped by the scheduler {at - killed_at:.1f} s after its kill"

    def logs(self, chars: int = 4000) -> str:
        """The last `chars` of the scheduler's and every host's logs, for a failing drill's message: what the
        flow's own log cannot say (when the scheduler dropped a host, what a worker did meanwhile)."""
        files = [self.root / "scheduler.log",
                 *(folder / name for folder in self.roots.values() for name in ("worker.log", "prefect-worker.log"))]
        return "".join(f"\n--- {path.relative_to(self.root)} ---\n{path.read_text()[-chars:]}"
                       for path in files if path.exists())

    def wait_until_holding(self, client, host: str, timeout: float = 120, alive=lambda: True) -> list[str]:
        """Wait until the scheduler has given `host` a task; the keys it holds."""
        deadline, address = time.monotonic() + timeout, self.address_of(client, host)
        while True:
            if held := list(client.processing().get(address, ())):
                return held
            assert alive() and time.monotonic() < deadline, f"{host} was never given a shard"
            time.sleep(0.05)


@contextmanager
def dask_hosts(root: Path, hosts: tuple[str, ...], environ: Mapping[str, str],
               prefect_pool: str | None = None) -> Iterator[DaskHosts]:
    """A scheduler and a worker per host, ready; with `prefect_pool`, also `prefect worker start --pool
    <pool> --work-queue <host>` per host (its output in <host>/prefect-worker.log). `environ` is each
    worker's whole environment but for HOME and PYTHONPATH (this checkout: the hosts run the same code,
    as `make setup` on each would). Prefect 3.8.8's worker ignores SIGTERM (docs/scale-out.md): SIGKILL."""
    dask = str(Path(sys.executable).parent / "dask")
    port = _free_port()
    # A worker whose process is alive but does not answer (frozen) is dropped after the scheduler's worker-ttl,
    # checked every worker-ttl: 5-10 min at Dask's 5 min default. CI once waited 511 s on a gather with nothing
    # logged, which such a worker may explain (the drill's message now carries the logs that would say). 60 s:
    # 1-2 min (docs/scale-out.md); a worker it drops wrongly would leave a drill one host short.
    processes = {"scheduler": subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                                "--no-dashboard"], cwd=root, start_new_session=True,
                                               env={**os.environ, "DASK_DISTRIBUTED__SCHEDULER__WORKER_TTL": "60s"},
                                               stdout=(root / "scheduler.log").open("w"), stderr=subprocess.STDOUT)}
    address, roots = f"tcp://127.0.0.1:{port}", {name: root / name for name in hosts}
    try:
        for name, folder in roots.items():
            (folder / "home").mkdir(parents=True)
            env = {**environ, "HOME": str(folder / "home"), "PYTHONPATH": os.pathsep.join(sys.path)}
            env.pop("PWD", None)
            processes[name] = subprocess.Popen(
                [dask, "worker", address, "--nthreads", "1", "--nworkers", "1", "--no-nanny", "--name", name,
                 "--no-dashboard", "--local-directory", str(folder / "dask")], cwd=folder, env=env,
                start_new_session=True, stdout=(folder / "worker.log").open("w"), stderr=subprocess.STDOUT)
            if prefect_pool:
                processes[f"{name}/prefect"] = subprocess.Popen(
                    [str(Path(sys.executable).parent / "prefect"), "worker", "start", "--pool", prefect_pool,
                     "--work-queue", name], cwd=folder, env=env, start_new_session=True,
                    stdout=(folder / "prefect-worker.log").open("w"), stderr=subprocess.STDOUT)
        from dask.distributed import Client

        with Client(address, timeout=60) as client:
            client.wait_for_workers(len(hosts), timeout=120)
        yield DaskHosts(address, root, roots, processes)
    finally:
        for process in processes.values():
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
            process.wait()
