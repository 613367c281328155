"""The history's insert state: failing since the first failure after a success, storing
again at the next success, and a reason an operator can act on."""

from __future__ import annotations

from datetime import UTC, datetime

from clickhouse_connect.driver.exceptions import DatabaseError

from mapservice.runtime.health import failing_reasons
from mapservice.runtime.insert_health import InsertHealth, code_of, describe, error_code

FULL = "Code: 243. DB::Exception: Cannot reserve 1.00 MiB, not enough space. (NOT_ENOUGH_SPACE)"
T0 = datetime(2026, 11, 25, 22, 15, 3, tzinfo=UTC).timestamp()


class Wall:
    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def test_before_any_insert_the_history_is_ready_with_no_reason() -> None:
    """Nothing tried yet: ready, nothing to explain, no last insert."""
    health = InsertHealth(Wall(T0))
    assert health() and not health.failing and health.reason() is None
    assert health.status() == {
        "storing": True,
        "failing_since_ms": None,
        "last_stored_ms": None,
        "reason": None,
    }


def test_a_failed_insert_makes_it_unready_naming_since_when_and_the_error() -> None:
    """The first failure sets the time; later failures keep it and count; the reason names
    the time (UTC), the ClickHouse error code, the message and what to do."""
    wall = Wall(T0)
    health = InsertHealth(wall)
    health.failed(RuntimeError(FULL))
    wall.t += 12
    health.failed(RuntimeError(FULL))
    assert not health() and health.failing and health.failures == 2
    reason = health.reason()
    assert reason.startswith(
        "inserts failing since 22:15:03Z (2 attempts): NOT_ENOUGH_SPACE: Code: 243."
    )
    assert "free disk space where ClickHouse keeps its data" in reason
    status = health.status()
    assert status["storing"] is False and status["failing_since_ms"] == int(T0 * 1000)
    assert status["reason"] == reason


def test_a_successful_insert_clears_the_failure_and_records_when() -> None:
    """Recovery is automatic: the next success is ready again, with its time kept."""
    wall = Wall(T0)
    health = InsertHealth(wall)
    health.failed(RuntimeError(FULL))
    wall.t += 30
    health.stored()
    assert health() and health.reason() is None and health.failures == 0
    assert health.status()["last_stored_ms"] == int((T0 + 30) * 1000)
    wall.t += 5
    health.failed(ConnectionError("connection refused"))
    assert health.status()["failing_since_ms"] == int(
        (T0 + 35) * 1000
    )  # a new failure, a new start


def test_errors_without_a_clickhouse_code_name_their_type_and_are_cut_short() -> None:
    """Any refusal counts (not only a full disk); a long message is cut to one short line."""
    assert error_code("connection refused") is None
    assert error_code(FULL) == "NOT_ENOUGH_SPACE"
    assert describe(ConnectionError("connection refused")) == "ConnectionError: connection refused"
    long = describe(RuntimeError("x" * 5000 + "\nsecond line"))
    assert long.startswith("RuntimeError: xxx") and long.endswith("...") and len(long) < 330
    health = InsertHealth(Wall(T0))
    health.failed(ConnectionError("connection refused"))
    assert health.reason().endswith(
        "ConnectionError: connection refused; the processors keep "
        "retrying and commit nothing unstored"
    )


def test_a_full_disk_over_clickhouse_http_says_what_to_do_like_embedded() -> None:
    """`mapservice up` inserts through the ClickHouse server: clickhouse-connect's error
    carries the code's name and ends its message with "(for url ...)". The reason still
    names NOT_ENOUGH_SPACE first and says to free disk space."""
    body = (
        "Code: 243. DB::Exception: Cannot reserve 1.00 MiB, not enough space: While "
        "executing SinkToStorage. (NOT_ENOUGH_SPACE) (version 25.8.2.1)"
    )
    url = "http://127.0.0.1:50837?query=INSERT+INTO+mapservice.poses"
    over_http = DatabaseError(
        f"Received ClickHouse exception, code: 243, server response: {body} (for url {url})",
        code=243,
        name="NOT_ENOUGH_SPACE",
    )
    as_text = RuntimeError(f"server response: {FULL} (for url {url})")
    for exc in (over_http, as_text):
        assert code_of(exc) == "NOT_ENOUGH_SPACE"
        assert describe(exc).startswith("NOT_ENOUGH_SPACE: ")
        health = InsertHealth(Wall(T0))
        health.failed(exc)
        assert "; free disk space where ClickHouse keeps its data; " in health.reason()
    assert code_of(DatabaseError("HTTP driver received HTTP status 502", name=None)) is None


def test_failing_reasons_come_from_failed_checks_that_can_explain() -> None:
    """Readiness names the cause for a check with a reason(); a plain check gives none."""
    health = InsertHealth(Wall(T0))
    health.failed(RuntimeError(FULL))
    checks = {"clickhouse": lambda: True, "kafka": lambda: False, "history_store": health}
    results = {name: bool(check()) for name, check in checks.items()}
    reasons = failing_reasons(checks, results)
    assert list(reasons) == ["history_store"] and "NOT_ENOUGH_SPACE" in reasons["history_store"]
    health.stored()
    assert failing_reasons(checks, {name: bool(check()) for name, check in checks.items()}) == {}


def test_one_kind_of_insert_succeeding_does_not_hide_another_failing() -> None:
    """Dead letters stored while the events are refused: still failing, since the events'
    first failure; ready only once every kind that failed succeeded."""
    wall = Wall(T0)
    health = InsertHealth(wall)
    health.failed(RuntimeError(FULL), "append_events")
    wall.t += 4
    health.failed(
        RuntimeError("Code: 252. DB::Exception: Too many parts. (TOO_MANY_PARTS)"),
        "append_dead_letters",
    )
    health.stored("derive_views")
    assert not health() and health.failing_since_s == T0
    health.stored("append_events")
    assert not health() and health.failing_since_s == T0 + 4
    assert "TOO_MANY_PARTS" in health.reason() and "merges fall behind" in health.reason()
    health.stored("append_dead_letters")
    assert health() and health.reason() is None and health.failures == 0


def test_a_health_port_probe_names_the_failing_inserts() -> None:
    """The processors' own /readyz (mapservice processors --health-port) carries the reason
    too, served as it is to the kubelet."""
    import json

    import httpx

    from mapservice.local.embedded import free_port
    from mapservice.runtime.health import probe_report
    from mapservice.runtime.health_server import serve_health

    health = InsertHealth(Wall(T0))
    readiness = {"clickhouse": lambda: True, "history_store": health}
    server = serve_health(
        "127.0.0.1", free_port(), lambda: probe_report({}), lambda: probe_report(readiness)
    )
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}/readyz"
        assert httpx.get(url).json() == {
            "ok": True,
            "checks": {"clickhouse": True, "history_store": True},
        }
        health.failed(RuntimeError(FULL))
        reply = httpx.get(url)
        body = json.loads(reply.text)
        assert reply.status_code == 503 and body["checks"]["history_store"] is False
        assert body["reasons"]["history_store"].startswith("inserts failing since 22:15:03Z")
    finally:
        server.shutdown()
        server.server_close()


def test_the_transitions_are_reported_for_the_log() -> None:
    """failed() says whether it started a failure, stored() how long one lasted if it ended it."""
    wall = Wall(T0)
    health = InsertHealth(wall)
    assert health.stored() is None
    assert health.failed(RuntimeError(FULL)) is True
    assert health.failed(RuntimeError(FULL)) is False
    wall.t += 15
    assert health.stored() == 15
    assert health.stored() is None
