"""The one retry helper, on tenacity: every place that tries again (the catalog waiting for DuckDB's
write lock, the worker pool re-running a unit whose worker died, the chat client's requests) says
what it retries, how often or how long, and how long it waits, here."""

from __future__ import annotations

import logging
from collections.abc import Callable

from tenacity import (Retrying, RetryCallState, retry_if_exception, stop_after_attempt, stop_after_delay, stop_any,
                      stop_never, wait_exponential, wait_fixed)


def retrying(
    when: Callable[[BaseException], bool],
    *,
    attempts: int | None = None,
    within_s: float | None = None,
    wait_s: float = 0.0,
    backoff_max_s: float | None = None,
    log: logging.Logger | None = None,
    what: str = "",
) -> Retrying:
    """Iterate it (`for attempt in retrying(...): with attempt: ...`) or call it (`retrying(...)(fn, *args)`):
    retries while `when(error)` holds, up to `attempts` tries in all and/or for `within_s` seconds,
    waiting `wait_s` (doubling up to `backoff_max_s` when set) between tries; then the last error is
    raised as it was. `log`: a warning before each new try, naming `what`."""
    stops = [*([stop_after_attempt(attempts)] if attempts is not None else []),
             *([stop_after_delay(within_s)] if within_s is not None else [])]
    wait = wait_exponential(multiplier=wait_s, max=backoff_max_s) if backoff_max_s is not None else wait_fixed(wait_s)

    def warn(state: RetryCallState) -> None:
        if log is not None:
            error = state.outcome.exception() if state.outcome else None
            log.warning("%s: %s; trying again (%d/%s)", what, error, state.attempt_number,
                        attempts - 1 if attempts is not None else
                        f"for up to {within_s:.0f} s" if within_s is not None else "until it succeeds")

    return Retrying(retry=retry_if_exception(when), stop=stop_any(*stops) if stops else stop_never, wait=wait,
                    before_sleep=warn, reraise=True)
