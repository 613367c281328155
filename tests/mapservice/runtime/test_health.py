"""Heartbeats and dependency checks: a stuck loop is not alive, a hung dependency is not
ready, and a probe never waits longer than its timeout."""

from __future__ import annotations

import threading
import time

from mapservice.runtime.health import CachedCheck, Heartbeat, kafka_check
from mapservice.settings import Settings


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_a_heartbeat_is_alive_while_recent() -> None:
    """Alive before the first beat (starting) and within max_age after one; dead after."""
    clock = Clock()
    beat = Heartbeat(max_age_s=10, clock=clock)
    assert beat.alive()
    beat.beat()
    clock.now += 9.9
    assert beat.alive()
    clock.now += 0.2
    assert not beat.alive() and beat.age_s() == 10.1


def test_a_hung_dependency_is_down_within_the_timeout() -> None:
    """A call that never returns: the check answers False after timeout_s, not later."""
    release = threading.Event()
    check = CachedCheck("hung", lambda: release.wait(30), ttl_s=0.0, timeout_s=0.2)
    started = time.monotonic()
    assert check() is False
    assert time.monotonic() - started < 1.0
    release.set()


def test_failures_and_false_are_down_successes_are_cached() -> None:
    """An exception or False is down; a success is reused for ttl_s without calling again."""
    calls = []

    def flaky():
        calls.append(1)
        if len(calls) == 1:
            raise ConnectionError("refused")
        return True

    clock = Clock()
    check = CachedCheck("flaky", flaky, ttl_s=5.0, timeout_s=1.0, clock=clock)
    assert check() is False
    clock.now += 5.1
    assert check() is True and check() is True and len(calls) == 2
    assert CachedCheck("false", lambda: False, ttl_s=0, timeout_s=1)() is False


def test_a_slow_refresh_keeps_the_last_answer_without_waiting() -> None:
    """Once a check has answered, a probe does not wait for a slow refresh (a busy
    ClickHouse): it gets the last answer at once, until the refresh is older than timeout_s."""
    release = threading.Event()
    calls = []

    def slow_after_first():
        calls.append(1)
        if len(calls) > 1:
            release.wait(30)
        return True

    check = CachedCheck("slow", slow_after_first, ttl_s=0.0, timeout_s=1.5)
    assert check() is True
    started = time.monotonic()
    assert check() is True  # the refresh hangs: the last answer, at once
    assert time.monotonic() - started < 0.5
    time.sleep(1.6)
    assert check() is False  # the refresh is older than timeout_s: down
    release.set()


def test_nowait_never_blocks_and_refreshes_in_the_background() -> None:
    """nowait(): None before any answer; then the last answer at once, a due refresh
    started in its own thread (what the API's async probes call on the event loop)."""
    release = threading.Event()
    calls = []

    def call():
        calls.append(1)
        if len(calls) > 1:
            release.wait(30)
        return True

    check = CachedCheck("bg", call, ttl_s=0.0, timeout_s=5.0)
    assert check.nowait() is None
    assert check() is True
    started = time.monotonic()
    assert check.nowait() is True and time.monotonic() - started < 0.05
    deadline = time.monotonic() + 2
    while len(calls) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert len(calls) == 2  # the refresh runs, in the background
    release.set()


def test_the_kafka_check_reuses_its_answer_for_the_configured_time() -> None:
    """MAPSERVICE_KAFKA_CHECK_TTL_S: a broker that is not there is asked again only once the
    last answer is that old (default 5 s), so /readyz notices a change within it."""
    clock = [0.0]
    for ttl_s in (0.5, 1.0, 5.0):
        calls = []
        settings = Settings(kafka_bootstrap="127.0.0.1:1", kafka_check_ttl_s=ttl_s)
        check = kafka_check(settings)
        assert check.ttl_s == ttl_s
        # The metadata call itself is swapped for a counter: what is tested is the reuse.
        check.call = lambda calls=calls: calls.append(1) or True
        check.clock = lambda: clock[0]
        assert check() is True and len(calls) == 1
        clock[0] += ttl_s * 0.9
        assert check() is True and len(calls) == 1  # reused
        clock[0] += ttl_s * 0.2
        assert check() is True and len(calls) == 2  # asked again
    assert Settings().kafka_check_ttl_s == 5.0
