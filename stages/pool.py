"""Fan units of work out to worker processes and hand each result back as it completes.

Workers are spawned, not forked: MuJoCo's GL contexts, torch's thread pools and Prefect's
event loop do not survive a fork. Each worker builds its own environments.
"""

from __future__ import annotations

import logging
import multiprocessing
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import TypeVar

Unit = TypeVar("Unit")
Result = TypeVar("Result")


class Progress:
    """Logs `stage: done/total units, rate, ETA` so a long run never goes silent."""

    def __init__(self, logger: logging.Logger, label: str, total: int, unit_name: str, rate_name: str):
        self.logger, self.label, self.total = logger, label, total
        self.unit_name, self.rate_name = unit_name, rate_name
        self.done = 0
        self.amount = 0
        self.started = time.monotonic()

    def advance(self, amount: int) -> None:
        self.done += 1
        self.amount += amount
        elapsed = max(time.monotonic() - self.started, 1e-6)
        eta = elapsed / self.done * (self.total - self.done)
        self.logger.info(
            "%s: %d/%d %s, %d %s, %.1f %s/s, ETA %.0fs",
            self.label, self.done, self.total, self.unit_name, self.amount, self.rate_name,
            self.amount / elapsed, self.rate_name, eta,
        )


def _init_worker() -> None:
    import torch

    torch.set_num_threads(1)  # one core per worker process; the pool supplies the parallelism


def _timed(work: Callable[[Unit], Result], unit: Unit) -> tuple[Result, float]:
    started = time.monotonic()
    return work(unit), time.monotonic() - started


def run_in_pool(
    work: Callable[[Unit], Result], units: Sequence[Unit], workers: int
) -> Iterator[tuple[Unit, Result, float]]:
    """Yield (unit, result, seconds in the worker) in completion order; the caller registers
    each before the next."""
    if not units:
        return
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=min(workers, len(units)), mp_context=context, initializer=_init_worker) as pool:
        futures = {pool.submit(_timed, work, unit): unit for unit in units}
        for future in as_completed(futures):
            result, seconds = future.result()
            yield futures[future], result, seconds
