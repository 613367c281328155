"""Retrying what must not be skipped: a batch that is not stored must not be acknowledged.

One policy for the processors (history inserts, live views and conflicts, whole consumer
batches): retry forever with exponential backoff capped at 10 s, log every failure with
what failed and when it is tried again. Cancellation is not an error: it stops at once.
"""

from __future__ import annotations

from collections.abc import Callable

import structlog
from tenacity import AsyncRetrying, RetryCallState, retry_if_exception_type, wait_exponential

log = structlog.get_logger(__name__)

MAX_DELAY_S = 10.0


def until_done(
    what: str, first_delay_s: float, on_failure: Callable[[], None] | None = None, **log_fields
) -> AsyncRetrying:
    """`async for attempt in until_done(...): with attempt: await ...` until it succeeds."""

    def before_sleep(state: RetryCallState) -> None:
        if on_failure is not None:
            on_failure()
        log.error(
            f"{what} failed, retrying",
            error=str(state.outcome.exception()),
            attempt=state.attempt_number,
            retry_in=round(state.next_action.sleep, 3) if state.next_action else None,
            **log_fields,
        )

    return AsyncRetrying(
        retry=retry_if_exception_type(Exception),
        wait=wait_exponential(multiplier=first_delay_s, max=MAX_DELAY_S),
        before_sleep=before_sleep,
        reraise=True,
    )
