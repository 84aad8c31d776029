"""The worker pool: real spawned processes, killed for real. A dead worker costs only its unit,
which runs again on a fresh worker; a unit that raises fails the run with its traceback."""

from __future__ import annotations

import ctypes
import os
import signal
import time
from pathlib import Path

import psutil
import pytest
from pydantic import BaseModel

from envs.pool import UnitFailed, WorkerLost, WorkerPool, interleaved, keep_workers, run_in_pool
from schemas.settings import SCENES_PER_WORKER_ENV, SettingError


class Job(BaseModel):
    n: int
    attempts_dir: str
    dies: str | None = None  # "sigkill" or "segfault" on the first attempt
    sleep_s: float = 0.0  # before it answers


def attempt(job: Job) -> tuple[int, int]:
    """Record the attempt; die on the first one if told to. -> (n squared, worker pid)."""
    attempts = Path(job.attempts_dir)
    first = not any(attempts.glob(f"{job.n}-*"))
    (attempts / f"{job.n}-{os.getpid()}-{len(list(attempts.iterdir()))}").touch()
    if first and job.dies == "sigkill":
        os.kill(os.getpid(), signal.SIGKILL)
    if first and job.dies == "segfault":
        ctypes.string_at(0)  # reads address 0: SIGSEGV
    time.sleep(job.sleep_s)
    if job.n < 0:
        raise ValueError(f"negative job {job.n}")
    return job.n * job.n, os.getpid()


def test_a_killed_and_a_crashed_worker_cost_only_their_own_units(tmp_path):
    jobs = [Job(n=n, attempts_dir=str(tmp_path), dies={3: "sigkill", 6: "segfault"}.get(n)) for n in range(10)]
    results = {job.n: result for job, result, _ in run_in_pool(attempt, jobs, workers=2)}
    assert {n: square for n, (square, _) in results.items()} == {n: n * n for n in range(10)}
    tries = {n: len(list(tmp_path.glob(f"{n}-*"))) for n in range(10)}
    assert tries == {n: 2 if n in (3, 6) else 1 for n in range(10)}  # nobody else ran twice
    # each death took its own process, and the unit retried after the second ran in a third: a replacement
    # (which live worker ran what is the scheduler's: the surviving original may run all the rest)
    attempts = sorted((int(order), int(n), int(pid)) for n, pid, order in (p.name.split("-") for p in tmp_path.iterdir()))
    first_try = {}
    for _, n, pid in attempts:
        first_try.setdefault(n, pid)
    assert first_try[3] != first_try[6] and len({pid for _, _, pid in attempts}) >= 3, attempts


def test_run_names_how_the_worker_died_and_the_pool_replaces_it(tmp_path):
    with WorkerPool(1) as pool:
        with pytest.raises(WorkerLost, match=r"died \(killed by SIGKILL\) running job 3"):
            pool.run(attempt, Job(n=3, attempts_dir=str(tmp_path), dies="sigkill"), "job 3")
        (square, _), seconds = pool.run(attempt, Job(n=3, attempts_dir=str(tmp_path), dies="sigkill"), "job 3")
    assert square == 9 and 0 < seconds < 60  # the replacement's own run, not the dead worker's


def test_a_unit_that_raises_is_not_retried_and_says_why(tmp_path):
    jobs = [Job(n=-1, attempts_dir=str(tmp_path))]
    with pytest.raises(UnitFailed, match="ValueError: negative job -1"):
        list(run_in_pool(attempt, jobs, workers=1, label=lambda job: f"job {job.n}"))
    assert len(list(tmp_path.iterdir())) == 1


def endpoint_gone(job: Job) -> None:
    from policies.openai_chat import ChatUnavailable

    raise ChatUnavailable(f"VLM explorer at http://vlm/{job.n} did not answer (timeout) after 3 tries", ["timeout"] * 3)


def test_a_known_failure_in_a_worker_arrives_as_itself_to_be_said_in_one_line(tmp_path):
    """A Sim2ActError raised in a worker (an endpoint that does not answer) was UnitFailed with a traceback
    in the terminal; it arrives as itself, its failures and the worker's traceback (a note) kept."""
    from policies.openai_chat import ChatUnavailable

    with pytest.raises(ChatUnavailable, match=r"^VLM explorer at http://vlm/7 did not answer") as raised:
        list(run_in_pool(endpoint_gone, [Job(n=7, attempts_dir=str(tmp_path))], workers=1, label=lambda job: f"job {job.n}"))
    assert raised.value.failures == ["timeout"] * 3 and "job 7 failed in its worker" in raised.value.__notes__[0]


def test_units_that_finished_before_a_failure_is_handed_back_still_reach_the_caller(tmp_path):
    """The caller registers each result as it comes; while it was busy, one unit failed and then another
    finished: that one is handed back before the failure is raised, not dropped with the rest."""
    jobs = [Job(n=1, attempts_dir=str(tmp_path)), Job(n=-1, attempts_dir=str(tmp_path), sleep_s=0.5),
            Job(n=2, attempts_dir=str(tmp_path), sleep_s=1.0)]
    handed = []
    with pytest.raises(UnitFailed, match="negative job -1"):
        for job, (square, _), _ in run_in_pool(attempt, jobs, workers=3, label=lambda job: f"job {job.n}"):
            handed.append(job.n)
            time.sleep(2.5)  # registering it: meanwhile job -1 fails, then job 2 finishes
    assert handed == [1, 2]


def test_stages_under_keep_workers_share_one_pool_until_one_stops_early(tmp_path):
    """Two stages in a campaign run on the same two processes, which stay up between them; a stage
    that asks for fresh workers retires them and closes its own when it ends, the next gets new ones,
    kept again; a stage that fails closes the pool (its units may still run), the next gets fresh
    workers; leaving keep_workers closes the last."""

    def stage(first: int, fresh_workers: bool = False) -> set[int]:
        jobs = [Job(n=n, attempts_dir=str(tmp_path)) for n in range(first, first + 4)]
        return {pid for _, (_, pid), _ in run_in_pool(attempt, jobs, workers=2, fresh_workers=fresh_workers)}

    def workers() -> set[int]:  # spawned workers: not multiprocessing's resource tracker, nor other tests' servers
        found = set()
        for child in psutil.Process().children():
            try:
                if child.status() != psutil.STATUS_ZOMBIE and "spawn_main" in " ".join(child.cmdline()):
                    found.add(child.pid)
            except psutil.Error:  # ended meanwhile
                pass
        return found

    with keep_workers():
        explore = stage(0)
        kept = workers()
        assert len(kept) == 2 and explore <= kept
        assert stage(10) <= kept and workers() == kept
        trained = stage(30, fresh_workers=True)
        assert len(trained) <= 2 and not trained & kept and not workers()  # the old ones gone, its own closed
        after_training = stage(40)
        kept = workers()
        assert len(kept) == 2 and after_training <= kept and not kept & trained
        with pytest.raises(UnitFailed):
            list(run_in_pool(attempt, [Job(n=-1, attempts_dir=str(tmp_path))], workers=2))
        after = stage(20)
        fresh = workers()
        assert after <= fresh and not fresh & kept
    assert not workers()  # closed on leaving, none left behind


def test_a_resumed_run_paces_its_eta_on_its_own_work(monkeypatch):
    """A training resumed at step 1,600 of 9,056 that ran 20 steps in 10 s has ~3,700 s to go, not the
    ~60 s that counting the earlier run's steps as this run's would say."""
    import logging

    import envs.pool as pool

    clock = iter([0.0, 10.0])
    monkeypatch.setattr(pool.time, "monotonic", lambda: next(clock))
    lines = []
    logger = logging.getLogger("test-progress")
    monkeypatch.setattr(logger, "info", lambda fmt, *args: lines.append(fmt % args))
    progress = pool.Progress(logger, "train", 9056, "steps", "samples")
    progress.resume_at(1600)
    progress.advance(20, 5120)
    assert lines == ["train: 1620/9056 steps, 5120 samples, 512.0 samples/s, ETA 3718s"]


def test_a_run_paused_midway_paces_its_eta_on_its_last_ten_minutes(monkeypatch):
    """A SAC at 10 env steps/s for 20 minutes, stopped (SIGSTOP) for 30 while the suite ran, then 15 minutes
    more at 10/s: its rate says 10/s again, not the 5.4/s of the whole run's average, pauses included."""
    import logging

    import envs.pool as pool

    now = [0.0]
    monkeypatch.setattr(pool.time, "monotonic", lambda: now[0])
    lines = []
    logger = logging.getLogger("test-progress")
    monkeypatch.setattr(logger, "info", lambda fmt, *args: lines.append(fmt % args))
    progress = pool.Progress(logger, "sac", 100_000, "env steps", "env steps")

    def run(seconds: int) -> None:
        for _ in range(seconds):
            now[0] += 1.0
            progress.advance(10, 10, log=False)

    run(20 * 60)
    assert progress.pace() == pytest.approx(10.0)
    now[0] += 30 * 60
    run(60)  # a minute after the pause the window still holds it: slow, and it says so
    assert progress.pace() < 2.0
    run(14 * 60)
    assert progress.pace() == pytest.approx(10.0)
    progress.advance(10, 10)
    assert lines == ["sac: 21010/100000 env steps, 21010 env steps, 10.0 env steps/s, ETA 7886s"]
    assert len(progress.samples) <= 602  # a sample a second over the window, not one per advance of the run


def test_interleaving_takes_each_group_in_turn_and_keeps_every_unit_once():
    units = ["nav-a0", "nav-a1", "nav-a2", "mw-b0", "rs-c0", "rs-c1"]
    order = interleaved(units, lambda u: u.split("-")[0])
    assert order == ["nav-a0", "mw-b0", "rs-c0", "nav-a1", "rs-c1", "nav-a2"]
    assert interleaved([], str) == []


def test_closing_a_pool_with_busy_workers_abandons_their_units_without_an_error():
    """A SIGTERM during an evaluation closes the pool while its threads wait on busy workers: each
    thread replaces the worker it lost as close() hangs up on the same pipes (once that was EBADF)."""
    import threading
    import time

    from envs.pool import PoolClosed, WorkerPool

    for _ in range(3):
        pool = WorkerPool(2)
        outcomes: list[BaseException | None] = []

        def busy() -> None:
            try:
                pool.run(time.sleep, 30, "sleep")
                outcomes.append(None)
            except BaseException as exc:  # noqa: BLE001 - what each thread ended with is the assertion
                outcomes.append(exc)

        threads = [threading.Thread(target=busy) for _ in range(2)]
        for thread in threads:
            thread.start()
        time.sleep(1.0)  # both units running in their workers
        pool.close()
        for thread in threads:
            thread.join(timeout=30)
        assert [type(o) for o in outcomes] == [PoolClosed, PoolClosed]
        assert all(w.connection.closed for w in pool._workers) and not any(w.process.is_alive() for w in pool._workers)


def test_a_bad_scenes_per_worker_is_refused_before_any_worker_starts(monkeypatch):
    monkeypatch.setenv(SCENES_PER_WORKER_ENV, "0")
    children = len(psutil.Process().children())
    with pytest.raises(SettingError, match="SIM2ACT_SCENES_PER_WORKER"):
        WorkerPool(2)
    assert len(psutil.Process().children()) == children
