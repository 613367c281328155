"""The processors' retry policy: forever, with capped exponential backoff, never on cancel."""

from __future__ import annotations

import asyncio

import pytest

from mapservice.runtime.retry import MAX_DELAY_S, until_done


async def _run(fn, failures: list) -> None:
    async for attempt in until_done("test step", 0.001, lambda: failures.append(1), step="x"):
        with attempt:
            await fn()


def test_retries_until_success_counting_each_failure() -> None:
    """Three failures then success: four calls, three failures reported, no exception."""
    calls, failures = [], []

    async def flaky() -> None:
        calls.append(1)
        if len(calls) <= 3:
            raise RuntimeError("store away")

    asyncio.run(_run(flaky, failures))
    assert (len(calls), len(failures)) == (4, 3)


def test_cancellation_is_not_retried() -> None:
    """A cancelled step stops at once instead of being retried."""
    calls, failures = [], []

    async def cancelled() -> None:
        calls.append(1)
        raise asyncio.CancelledError

    with pytest.raises(asyncio.CancelledError):
        asyncio.run(_run(cancelled, failures))
    assert (len(calls), failures) == (1, [])


def test_backoff_doubles_from_the_first_delay_up_to_the_cap() -> None:
    """Delays are first, 2x first, 4x first, ... never above MAX_DELAY_S."""
    waits = [until_done("x", 0.2).wait(_State(n)) for n in range(1, 10)]
    assert waits[:4] == pytest.approx([0.2, 0.4, 0.8, 1.6]) and max(waits) == MAX_DELAY_S


class _State:
    def __init__(self, attempt_number: int) -> None:
        self.attempt_number = attempt_number
