"""The soak: a campaign SIGKILLed at random moments and resumed each time, its finished parts checked
after every kill (issue 11 item 5). `sim2act bench soak` with a campaign's flags:

    sim2act bench soak --preset generalist --workspace /data/generalist --kills 10 --out docs/soak.md

`soak()` runs `sim2act run` with those flags as a child process and:
1. starts the campaign (the first start resumes whatever the workspace holds);
2. after a random wait (seeded), SIGKILLs one of its processes: the flow (the `sim2act run` process
   itself, whose watchdog then kills the rest), a worker (a rollout worker; while training, a
   DataLoader worker), or Prefect's API server, the three kinds in turn so each is hit;
3. waits for the campaign to end. A killed rollout worker is replaced and its shard retried in place
   (flows/rollouts.py), so the campaign may go on: that kill is checked at the next end;
4. once the campaign has ended, snapshots the catalog (every registered shard's path, rows and sha256;
   every finished unit) and checks that every earlier snapshot is still in it, unchanged, and that
   every registered file is whole (`Catalog.verify`: a bad one would be quarantined and named);
5. restarts at 1 until `kills` kills are done, then lets the campaign finish (exit status 0), or
   until the soak itself gets SIGINT or SIGTERM (a campaign longer than one sitting: it stops the
   campaign as a kill would, checks, and reports);
6. checks every registered file's sha256 on disk (`verify(full=True)`) and reports each kill: what,
   when, the units finished by then, and the seconds until the next unit was registered. The report
   is rewritten after every check, so a soak that is itself killed keeps what it saw.
"""

from __future__ import annotations

import datetime
import logging
import random
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import psutil
from pydantic import BaseModel

from schemas.errors import Sim2ActError
from schemas.workspace import Workspace
from warehouse.catalog import Catalog

log = logging.getLogger("sim2act.bench.soak")

KINDS = ("flow", "worker", "server")


class SoakFailed(Sim2ActError, RuntimeError):
    """The campaign under the soak failed without a kill (its own error is in its log)."""

EXIT_WAIT_S = 120.0  # how long a kill may take to end the campaign before it counts as survived in place
GONE_WAIT_S = 30.0  # how long the killed campaign's processes may outlive it (its watchdog polls at 0.25 s)


class Kill(BaseModel):
    number: int
    kind: str  # flow | worker | server
    pid: int
    at: datetime.datetime  # UTC
    start_to_kill_s: float  # since this start of the campaign
    units_then: int  # units finished when the campaign was next seen ended (checked there)
    campaign_ended: bool  # the kill ended the campaign (else it went on: a replaced worker)
    outlived: int = 0  # the campaign's processes still alive GONE_WAIT_S after it ended (then killed here)
    outlived_what: list[str] = []  # their command lines, to tell which kind its watchdog missed
    next_unit_s: float | None = None  # from the kill to the next unit registered


class Check(BaseModel):
    when: str  # "start", "after kill N" (the campaign seen ended after N kills), "end"
    units: int
    shards: int
    kept: bool  # every earlier snapshot's units and shards are here with the same rows and sha256
    bad_files: list[str]  # registered files found missing or torn (quarantined)


class Soak(BaseModel):
    command: list[str]
    seed: int
    kills: list[Kill]
    checks: list[Check]
    starts: int
    wall_s: float
    ended: str  # "finished" (exit status 0 after every kill), "finished after K of N kills", or "stopped" (told to)
    final_sha256_ok: bool | None  # every check kept the finished parts whole (the end's re-hashes all); None until then
    unit_gap_median_s: float | None  # the campaign's usual time between two registered units


def _tree(pid: int) -> list[psutil.Process]:
    try:
        parent = psutil.Process(pid)
        return [parent, *parent.children(recursive=True)]
    except psutil.NoSuchProcess:
        return []


def _victim(run_pid: int, kind: str) -> psutil.Process | None:
    """The process of `kind` in the campaign's tree: the run itself, a rollout worker (a
    multiprocessing child), or Prefect's temporary API server (uvicorn); None if it has none now."""
    if kind == "flow":
        return next(iter(_tree(run_pid)), None)
    for process in _tree(run_pid)[1:]:
        try:
            cmdline = " ".join(process.cmdline())
        except psutil.Error:
            continue
        if kind == "worker" and "multiprocessing" in cmdline and "spawn_main" in cmdline:
            return process
        if kind == "server" and "uvicorn" in cmdline:
            return process
    return None


def _snapshot(catalog: Catalog) -> tuple[set[str], dict[str, tuple[int, str]]]:
    if not catalog.path.exists():
        return set(), {}
    units = {key for (key,) in catalog.query("SELECT unit_key FROM stage_runs")}
    shards = {path: (rows, sha) for path, rows, sha in catalog.query("SELECT path, num_rows, sha256 FROM shards")}
    return units, shards


def soak(run_args: Sequence[str], workspace: Path, kills: int, seed: int, wait_s: tuple[float, float],
         log_folder: Path, on_check: Callable[[Soak], None] = lambda result: None,
         kinds: Sequence[str] = KINDS) -> Soak:
    """Run the campaign `sim2act run <run_args>` through `kills` SIGKILLs to its end, or until this
    process gets SIGINT or SIGTERM (steps in the module docstring); `on_check` gets the report so far
    after every check; `kinds` the processes to kill, in turn (shuffled). Raises RuntimeError when the
    campaign fails without having been killed."""
    rng = random.Random(seed)
    order = [kinds[i % len(kinds)] for i in range(kills)]
    rng.shuffle(order)
    command = [sys.executable, "-m", "flows.cli", "run", *run_args]
    catalog = Catalog(Workspace.at(workspace).catalog)
    log_folder.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    result = Soak(command=command, seed=seed, kills=[], checks=[], starts=0, wall_s=0.0, ended="", final_sha256_ok=None,
                  unit_gap_median_s=None)
    seen: tuple[set[str], dict[str, tuple[int, str]]] = (set(), {})
    stop = []
    previous = {sig: signal.signal(sig, lambda *_: stop.append(True)) for sig in (signal.SIGINT, signal.SIGTERM)}

    def check(when: str, full: bool = False) -> Check:
        nonlocal seen
        bad = [path for path, _ in catalog.verify(full=full)] if catalog.path.exists() else []
        units, shards = _snapshot(catalog)
        kept = seen[0] <= units and all(shards.get(path) == value for path, value in seen[1].items())
        found = Check(when=when, units=len(units), shards=len(shards), kept=kept, bad_files=bad)
        log.info("soak: check %s: %d units, %d shards, earlier parts kept: %s, bad files: %d",
                 when, len(units), len(shards), kept, len(bad))
        if not kept or bad:
            log.error("soak: a kill cost finished work: %s", found)
        seen = (units, shards)
        result.checks.append(found)
        for kill in result.kills:  # the kills since the last check: what had finished by then
            if kill.units_then < 0:
                kill.units_then = found.units
        result.wall_s = time.monotonic() - started
        on_check(result)
        return found

    def waiting(run: subprocess.Popen, seconds: float) -> bool:
        """Sleep up to `seconds` while the campaign runs; False if it ended or the soak was told to stop."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and run.poll() is None and not stop:
            time.sleep(0.5)
        return run.poll() is None and not stop

    try:
        check("start")
        while not stop:
            result.starts += 1
            with open(log_folder / f"run-{result.starts:02d}.log", "wb") as out:
                run = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
            run_started = time.monotonic()
            killed_this_run = False
            while len(result.kills) < kills and waiting(run, rng.uniform(*wait_s)):
                kill = _kill(run, order[len(result.kills)], len(result.kills) + 1, run_started)
                if kill is not None:
                    killed_this_run = True
                    result.kills.append(kill)
                    log.info("soak: kill %d/%d: SIGKILLed the %s (pid %d), %.0f s into start %d: %s",
                             kill.number, kills, kill.kind, kill.pid, kill.start_to_kill_s, result.starts,
                             "the campaign ended" if kill.campaign_ended else "the campaign went on")
            while run.poll() is None and not stop:
                time.sleep(0.5)
            if stop and run.poll() is None:  # told to stop: end the campaign as a kill would
                _end(run)
            code = run.wait()
            check("after the stop" if stop else f"after kill {len(result.kills)}" if result.kills else "after the run")
            if code == 0:  # ended on its own: with fewer kills than asked, a start again would only finish again
                result.ended = "finished" if len(result.kills) >= kills else f"finished after {len(result.kills)} of {kills} kills"
                break
            if code != 0 and not killed_this_run and not stop:
                raise SoakFailed(f"soak: the campaign failed on its own (exit {code}); see {out}")
        result.ended = result.ended or "stopped"
        check("end", full=True)
        # every check, not the last alone: a unit a kill tore is quarantined and made again, so the end looks whole
        result.final_sha256_ok = all(c.kept and not c.bad_files for c in result.checks)
        # what each kill cost: from it to the next unit registered, beside the usual gap between two
        finished = sorted(at for (at,) in catalog.query("SELECT finished_at FROM stage_runs")) if catalog.path.exists() else []
        for kill in result.kills:
            after = next((t for t in finished if t > kill.at), None)
            kill.next_unit_s = None if after is None else (after - kill.at).total_seconds()
        gaps = [(b - a).total_seconds() for a, b in zip(finished, finished[1:])]
        result.unit_gap_median_s = statistics.median(gaps) if gaps else None
        result.wall_s = time.monotonic() - started
        on_check(result)
        return result
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _kill(run: subprocess.Popen, kind: str, number: int, run_started: float) -> Kill | None:
    """SIGKILL the campaign's process of `kind` (the flow where it has none of that kind now: no
    rollouts running), wait for the campaign to end (or EXIT_WAIT_S: it went on), and for everything
    it started to be gone. None if the process was already gone."""
    victim = _victim(run.pid, kind)
    if victim is None:
        kind, victim = "flow", _victim(run.pid, "flow")
    tree = _tree(run.pid)
    at = datetime.datetime.now(datetime.timezone.utc).replace(tzinfo=None)
    try:
        victim.send_signal(signal.SIGKILL)
    except (psutil.NoSuchProcess, AttributeError):
        return None
    kill = Kill(number=number, kind=kind, pid=victim.pid, at=at, start_to_kill_s=time.monotonic() - run_started,
                units_then=-1, campaign_ended=False)
    try:
        run.wait(timeout=EXIT_WAIT_S)
        kill.campaign_ended = True
    except subprocess.TimeoutExpired:
        return kill
    _, alive = psutil.wait_procs([p for p in tree if p.pid != run.pid], timeout=GONE_WAIT_S)
    alive = [p for p in alive if _running(p)]  # a zombie is dead, only not yet reaped by its new parent
    kill.outlived = len(alive)  # its watchdog (flows/lifetime.py) should have left none
    for process in alive:
        try:
            kill.outlived_what.append(" ".join(process.cmdline())[:200] or process.name())
        except psutil.Error:
            kill.outlived_what.append(f"pid {process.pid}")
        try:
            process.kill()
        except psutil.Error:
            pass
    if alive:
        log.error("soak: kill %d: %d process(es) outlived the campaign by %.0f s: %s", number, len(alive),
                  GONE_WAIT_S, kill.outlived_what)
    return kill


def _running(process: psutil.Process) -> bool:
    try:
        return process.status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def _end(run: subprocess.Popen) -> None:
    """Stop the campaign when the soak is told to stop: SIGKILL, as the soak's kills do (a kill loses at
    most the units in flight), and whatever it started after it."""
    tree = _tree(run.pid)
    run.kill()
    run.wait()
    _, alive = psutil.wait_procs(tree[1:], timeout=GONE_WAIT_S)
    for process in alive:
        process.kill()


def markdown(result: Soak, command_line: str) -> str:
    lines = [
        "# Soak: a campaign SIGKILLed and resumed", "",
        f"`{command_line}` (seed {result.seed}): {len(result.kills)} kills, {result.starts} starts, "
        f"{result.wall_s / 3600:.2f} h in all, {result.ended or 'running'}. Finished parts at every check, and every "
        "registered file's sha256 at the end: "
        + {None: "not checked yet", True: "as registered",
           False: "SOME DIFFER OR WENT MISSING (the checks below say when)"}[result.final_sha256_ok]
        + (f"; the campaign's usual gap between two registered units {result.unit_gap_median_s:.1f} s (median)."
           if result.unit_gap_median_s is not None else "."), "",
        "| kill | what | into its start | ended the campaign | units finished then | outlived it | next unit after |",
        "|---|---|---|---|---|---|---|",
    ]
    for k in result.kills:
        lines.append(f"| {k.number} | {k.kind} (pid {k.pid}) | {k.start_to_kill_s:.0f} s | "
                     f"{'yes' if k.campaign_ended else 'no (went on)'} | {k.units_then:,} | {k.outlived} | "
                     f"{'-' if k.next_unit_s is None else f'{k.next_unit_s:.0f} s'} |")
    lines += ["", "| check | units | shards | earlier parts kept | bad files |", "|---|---|---|---|---|"]
    for c in result.checks:
        lines.append(f"| {c.when} | {c.units:,} | {c.shards:,} | {'yes' if c.kept else 'NO'} | "
                     f"{', '.join(c.bad_files) or 'none'} |")
    return "\n".join(lines) + "\n"
