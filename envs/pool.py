"""Fan units of work out to long-lived worker processes and hand each result back as it completes.

Workers are spawned, not forked: MuJoCo's GL contexts, torch's thread pools and Prefect's
event loop do not survive a fork. Each worker keeps its environments across units. A worker
that dies (killed, segfault, out of memory) takes only its unit in flight with it: the pool
starts a fresh worker and the caller retries that unit; the other workers go on.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import queue
import signal
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Hashable, Iterator, Sequence
from contextlib import contextmanager
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Any, TypeVar

from schemas.errors import Sim2ActError
from schemas.retry import retrying
from schemas.settings import scenes_per_worker

Unit = TypeVar("Unit")
Result = TypeVar("Result")
log = logging.getLogger("sim2act.envs.pool")
RETRIES = 2  # a unit whose worker died is run again this many times before the stage fails
# Rate and ETA are paced on about the last 10 minutes, not the whole run: a run paused (SIGSTOP while
# the suite ran beside a day-long SAC) or sped up midway (a neighbour finished) would otherwise carry
# that pace to its end. Long enough to average over a few of a slow unit's log lines.
PACE_WINDOW_S = 600.0


class WorkerLost(RuntimeError):
    """The worker process running a unit died before answering."""


class UnitFailed(RuntimeError):
    """The unit raised inside its worker; the message carries the worker's traceback."""


class PoolClosed(RuntimeError):
    """The pool was closed (its caller stopped) while a unit waited or ran: not to be retried."""


class Progress:
    """A live bar on a terminal (done/total, rate, ETA) and a log line per finished unit, so a
    long run never goes silent; `on_update(fraction)` feeds other displays (a Prefect artifact)."""

    def __init__(
        self, logger: logging.Logger, label: str, total: int, count_name: str, rate_name: str,
        on_update: Callable[[float], None] | None = None,
    ):
        from tqdm import tqdm

        self.logger, self.label, self.total = logger, label, total
        self.count_name, self.rate_name, self.on_update = count_name, rate_name, on_update
        self.done = self.amount = 0
        self.done_before = 0  # done by an earlier run this one resumes: not part of this run's pace
        # (time, units this run did itself, amount) at most every second; the first is the oldest at least
        # PACE_WINDOW_S old (or the run's start), which rate and ETA are measured from
        self.samples: deque[tuple[float, int, int]] = deque([(time.monotonic(), 0, 0)])
        # disable=None: drawn only on a terminal; logs and Prefect get the lines below
        self.bar = tqdm(total=total, desc=label, unit=count_name, disable=None, leave=False, file=sys.stderr)

    def advance(self, count: int, amount: int, log: bool = True) -> None:
        """`log=False`: the bar moves, no log line (units far shorter than a log line's worth)."""
        self.done += count
        self.amount += amount
        now = time.monotonic()
        pace, rate = self._recent(now)
        eta = (self.total - self.done) / pace if pace > 0 else float("nan")
        if now - self.samples[-1][0] >= 1.0:
            self.samples.append((now, self.done - self.done_before, self.amount))
        self.bar.update(count)
        self.bar.set_postfix_str(f"{rate:.1f} {self.rate_name}/s", refresh=False)
        if log:
            self.logger.info(
                "%s: %d/%d %s, %d %s, %.1f %s/s, ETA %.0fs", self.label, self.done, self.total, self.count_name,
                self.amount, self.rate_name, rate, self.rate_name, eta,
            )
        if self.on_update is not None:
            self.on_update(self.done / max(self.total, 1))

    def pace(self) -> float:
        """Units per second this run did itself over about the last PACE_WINDOW_S (an earlier run's,
        resumed, not counted); 0 before any."""
        return self._recent(time.monotonic())[0]

    def _recent(self, now: float) -> tuple[float, float]:
        """(units/s, amount/s) this run did itself since its newest sample at least PACE_WINDOW_S old
        (its start, if none is): the samples older than that one are dropped."""
        while len(self.samples) > 1 and now - self.samples[1][0] >= PACE_WINDOW_S:
            self.samples.popleft()
        since, done, amount = self.samples[0]
        elapsed = max(now - since, 1e-6)
        return (self.done - self.done_before - done) / elapsed, (self.amount - amount) / elapsed

    def resume_at(self, done: int) -> None:
        """Move to `done`, the units between finished by an earlier run (a resumed checkpoint): the
        ETA paces the rest on what this run did itself."""
        skipped = done - self.done
        self.bar.update(skipped)
        self.done += skipped
        self.done_before += skipped

    def close(self) -> None:
        self.bar.close()


def interleaved(units: Sequence[Unit], group: Callable[[Unit], Hashable]) -> list[Unit]:
    """The units round-robin over their groups: the first of each group (groups in the order they
    first appear), then the second of each, and so on, each group's own order kept. A run in this
    order samples every group from its first minutes, so its rate and ETA speak for the whole run
    (the generalist's exploration, task after task, once said ETA 500 s with 1,180 s to go: its
    navigation ran 16x faster per step than the robosuite tasks left at the end), and a run
    stopped early holds some of every group."""
    groups: dict[Hashable, list[Unit]] = {}
    for unit in units:
        groups.setdefault(group(unit), []).append(unit)
    rounds = max((len(members) for members in groups.values()), default=0)
    return [members[turn] for turn in range(rounds) for members in groups.values() if turn < len(members)]


class StagesToStderr(logging.StreamHandler):
    """A StreamHandler on sys.stderr as it is at each line, not as it was when the handler was added: a command
    run twice in one process (a notebook's redirected stderr, a test's captured one) writes where stderr is now,
    never to a stream closed since (logging's "I/O operation on closed file", 99 lines of it in a refusal). As
    the standard library's own last-resort handler (logging._StderrHandler) does; its stream cannot be set."""

    def __init__(self) -> None:
        logging.Handler.__init__(self)  # not StreamHandler's, which would assign the stream

    @property
    def stream(self):  # type: ignore[override]
        return sys.stderr


def log_stages_to_stderr() -> None:
    """Where no Prefect handler takes the stages' log lines (`sim2act train`, `eval`, a pool worker's
    own lines), and the progress bar is drawn only on a terminal: without this, a run piped to a
    file is silent."""
    logger = logging.getLogger("sim2act")
    if not logger.handlers:
        handler = StagesToStderr()
        handler.setFormatter(logging.Formatter("%(asctime)s | %(levelname)-7s | %(name)s - %(message)s", "%H:%M:%S"))
        logger.addHandler(handler)
        logger.setLevel(logging.INFO)


def _init_worker() -> None:
    # One core per worker process; the pool supplies the parallelism. Said to torch through the
    # environment (read when a policy first imports it), not by importing torch here: that costs
    # every worker 1.2 s at start, and expert-only exploring never needs it.
    for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[variable] = "1"
    if "torch" in sys.modules:  # already imported (a script's __main__ that imports it, re-run by spawn): too late for the environment
        sys.modules["torch"].set_num_threads(1)


_exit_hooks: list[Callable[[], None]] = []  # this worker's, run when it is told to stop


def at_worker_exit(hook: Callable[[], None]) -> None:
    """In a pool worker, `hook` runs when the worker is told to stop (or its parent is gone), before
    the interpreter's teardown: unlike atexit, whose order is the order libraries happened to register
    in (MuJoCo's EGL display ends before the GL contexts made after it are freed). Elsewhere, never."""
    if hook not in _exit_hooks:
        _exit_hooks.append(hook)


def _leave() -> None:
    for hook in _exit_hooks:
        try:
            hook()
        except Exception:  # the process is ending: say so, and let the other hooks run
            traceback.print_exc()


def keeping_workers() -> bool:
    """Whether stages here borrow the kept pool (inside keep_workers)."""
    return _keeping


def _serve(connection: Connection) -> None:
    """A worker's loop: (work, unit) in, ("ok", result, seconds) or ("error", text, 0) out. However
    it ends (told to stop, the parent gone, an interrupt), its exit hooks run before the teardown."""
    _init_worker()
    try:
        _serve_units(connection)
    finally:
        _leave()


def _serve_units(connection: Connection) -> None:
    while True:
        try:
            message = connection.recv()
        except EOFError:  # the parent is gone
            return
        if message is None:
            return
        work, unit = message
        started = time.monotonic()
        try:
            connection.send(("ok", work(unit), time.monotonic() - started))
        except Exception as exc:  # the unit raised, or its result cannot be pickled back
            _send_failure(connection, exc, traceback.format_exc())


def _send_failure(connection: Connection, exc: Exception, text: str) -> None:
    """("error", (the worker's traceback, the exception if an OSError or a Sim2ActError that pickles), 0):
    see WorkerPool.run."""
    try:
        connection.send(("error", (text, exc if isinstance(exc, (OSError, Sim2ActError)) else None), 0.0))
    except Exception:  # it does not pickle (nothing was sent)
        connection.send(("error", (text, None), 0.0))


@dataclass
class _Worker:
    process: Any  # a spawned multiprocessing.Process
    connection: Connection


def _death(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        return f"killed by {signal.Signals(-exitcode).name}"
    return f"exit code {exitcode}"


def _failure(label: str, text: str, error: OSError | Sim2ActError | None) -> Exception:
    """What a unit that raised raises here: an OSError (a full disk, a permission) is the machine's,
    not the unit's, and a Sim2ActError a known failure (an endpoint that does not answer), so each stays
    itself (`sim2act` says it in one line), the worker's traceback added as a note; anything else is
    UnitFailed carrying that traceback."""
    if error is None:
        return UnitFailed(f"{label} failed in its worker:\n{text}")
    error.add_note(f"{label} failed in its worker:\n{text}")
    return error


class WorkerPool:
    """`workers` spawned processes, each running one unit at a time; `run` is thread-safe and
    blocks until its unit is done."""

    def __init__(self, workers: int):
        """Raises:
            SettingError: SIM2ACT_SCENES_PER_WORKER is not a whole number ≥ 1 (said here, before any
                worker starts, rather than by each worker at its first unit).
        """
        scenes_per_worker()
        self.size = workers
        self._context = multiprocessing.get_context("spawn")
        self._idle: queue.Queue[_Worker] = queue.Queue()
        self._lock = threading.Lock()
        self._workers: list[_Worker] = []
        self._closed = False
        with self._lock:
            for _ in range(workers):
                self._idle.put(self._start())

    def _start(self) -> _Worker:
        """A fresh worker, registered; the caller holds the lock (so close() sees every worker)."""
        parent, child = self._context.Pipe()
        process = self._context.Process(target=_serve, args=(child,), daemon=True, name="sim2act-worker")
        process.start()
        child.close()
        worker = _Worker(process, parent)
        self._workers.append(worker)
        return worker

    def run(self, work: Callable[[Unit], Result], unit: Unit, label: str = "") -> tuple[Result, float]:
        """(result, seconds in the worker); WorkerLost if the worker died, UnitFailed if it raised
        (an OSError: that error itself), PoolClosed if the pool was closed meanwhile."""
        label = label or repr(unit)
        worker = self._next_idle()
        try:
            worker.connection.send((work, unit))
            wait([worker.connection, worker.process.sentinel])
            status, payload, seconds = worker.connection.recv()  # EOFError: it died first
        except BaseException as failure:  # a worker in an unknown state is never reused
            died = isinstance(failure, (EOFError, OSError))
            self._replace(worker)
            if self._closed:
                raise PoolClosed(f"the pool was closed while {label} ran") from None
            if died:
                raise WorkerLost(f"worker {worker.process.pid} died ({_death(worker.process.exitcode)}) running {label}") from None
            raise
        self._idle.put(worker)
        if status == "error":
            raise _failure(label, *payload)
        return payload, seconds

    def _replace(self, worker: _Worker) -> None:
        if worker.process.is_alive():
            worker.process.kill()
        worker.process.join(timeout=5)
        self._hang_up(worker)
        with self._lock:
            self._workers.remove(worker)
            if not self._closed:
                self._idle.put(self._start())

    def _next_idle(self) -> _Worker:
        while True:
            try:
                return self._idle.get(timeout=1.0)
            except queue.Empty:
                if self._closed:
                    raise PoolClosed("the pool was closed") from None

    def close(self) -> None:
        """Idle workers are told to stop (their environments close cleanly); busy ones are
        terminated, their units abandoned: the caller has stopped."""
        with self._lock:
            self._closed = True
            workers = list(self._workers)
        idle = set()
        while not self._idle.empty():
            worker = self._idle.get_nowait()
            idle.add(id(worker))
            try:
                worker.connection.send(None)
            except OSError:  # it died while idle
                pass
        for worker in workers:
            if id(worker) not in idle:
                worker.process.terminate()
        for worker in workers:
            worker.process.join(timeout=10)
            if worker.process.is_alive():
                worker.process.kill()
                worker.process.join()
            self._hang_up(worker)

    def _hang_up(self, worker: _Worker) -> None:
        # close() and a run() replacing the worker it lost may both close one pipe at once: twice
        # at the same moment is EBADF (a SIGTERM during an evaluation ended in that traceback)
        with self._lock:
            if not worker.connection.closed:
                worker.connection.close()

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def run_with_retries(
    pool: WorkerPool, work: Callable[[Unit], Result], unit: Unit, label: str = "", retries: int = RETRIES
) -> tuple[Result, float]:
    """Run `unit`, again on a fresh worker if its worker died; a unit that raises is not retried."""
    again = retrying(lambda error: isinstance(error, WorkerLost), attempts=retries + 1, log=log, what=label or "a unit")
    return again(pool.run, work, unit, label)


_keeping = False  # inside keep_workers(): stages borrow _kept instead of starting their own pool
_kept: WorkerPool | None = None  # the pool they share, started when a stage first asks
_kept_lock = threading.Lock()


@contextmanager
def keep_workers() -> Iterator[None]:
    """Within it, the stages share one pool, started when first asked for and closed on leaving:
    a campaign's explore, evaluate and baselines reuse the same worker processes, and the scenes
    they built (~3 s a robosuite scene per worker), instead of each stage spawning its own.
    Re-entrant: an inner one (a stage run inside a campaign) keeps the outer's pool."""
    global _keeping, _kept
    if _keeping:
        yield
        return
    _keeping = True
    try:
        yield
    finally:
        with _kept_lock:
            pool, _kept, _keeping = _kept, None, False
        if pool is not None:
            pool.close()


@contextmanager
def borrowed_pool(workers: int, fresh: bool = False) -> Iterator[WorkerPool]:
    """A pool of at least `workers` processes: the kept one (grown if it is smaller) or, outside
    keep_workers, a fresh one closed on return. A borrower that leaves early (an error, or its caller
    stopped) may leave units running: the pool is closed then, and the next borrower gets a fresh one.
    `fresh` retires the kept pool first, and with it the scenes earlier stages built in its workers,
    then runs on processes of its own, closed on return with what its long units left in them (the
    RL baselines' replays and scenes): the stages after get a new pool, kept."""
    global _kept
    if fresh and _keeping:
        with _kept_lock:
            if _kept is not None:
                _kept.close()
                _kept = None
    if fresh or not _keeping:
        with WorkerPool(workers) as pool:
            yield pool
        return
    with _kept_lock:
        if _kept is not None and _kept.size < workers:
            _kept.close()
            _kept = None
        if _kept is None:
            _kept = WorkerPool(workers)
        pool = _kept
    try:
        yield pool
    except BaseException:
        with _kept_lock:
            if _kept is pool:
                _kept = None
        pool.close()
        raise


def run_in_pool(
    work: Callable[[Unit], Result], units: Sequence[Unit], workers: int, label: Callable[[Unit], str] = repr,
    fresh_workers: bool = False,
) -> Iterator[tuple[Unit, Result, float]]:
    """Yield (unit, result, seconds in the worker) in completion order; the caller registers
    each before the next. Stopping early (an error, or the caller's) abandons the rest.
    `fresh_workers`: on processes that hold nothing from earlier stages, closed after this one
    (`borrowed_pool`'s `fresh`), for units that run for hours on a few scenes of their own."""
    if not units:
        return
    count = min(workers, len(units))
    with borrowed_pool(count, fresh_workers) as pool:
        threads = ThreadPoolExecutor(max_workers=count, thread_name_prefix="sim2act-pool")
        try:
            futures = {threads.submit(run_with_retries, pool, work, unit, label(unit)): unit for unit in units}
            handed = set()
            for future in as_completed(futures):
                if future.exception() is not None:
                    # units that finished while the caller was busy are its to register before the failure
                    # ends the run (those still running are abandoned with the pool)
                    for other in futures:
                        if other not in handed and other.done() and not other.cancelled() and not other.exception():
                            result, seconds = other.result()
                            yield futures[other], result, seconds
                    future.result()  # raises
                result, seconds = future.result()
                handed.add(future)
                yield futures[future], result, seconds
        finally:
            threads.shutdown(wait=False, cancel_futures=True)
