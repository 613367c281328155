"""An API apart from the processors says whether the history is stored as they do: their
health endpoint's /history-status, read by ProcessorsStatus (readiness and the banner)."""

from __future__ import annotations

import time

import httpx

from mapservice.adapters.processors_status import ProcessorsStatus
from mapservice.local.embedded import free_port
from mapservice.runtime.health import probe_report
from mapservice.runtime.health_server import serve_health
from mapservice.runtime.insert_health import InsertHealth


def processors_health(health: InsertHealth):
    port = free_port()
    server = serve_health(
        "127.0.0.1", port, lambda: {"ok": True}, documents={"/history-status": health.status}
    )
    return server, f"http://127.0.0.1:{port}"


def test_the_processors_health_endpoint_serves_the_inserts_state() -> None:
    health = InsertHealth()
    health.stored()
    server, url = processors_health(health)
    try:
        doc = httpx.get(url + "/history-status", timeout=5).json()
        assert doc["storing"] is True and doc["reason"] is None and doc["last_stored_ms"]
        assert httpx.get(url + "/nothing", timeout=5).status_code == 404
    finally:
        server.shutdown()


def test_the_api_apart_reports_a_full_disk_as_the_processors_see_it() -> None:
    health = InsertHealth()
    health.stored()
    server, url = processors_health(health)
    try:
        status = ProcessorsStatus(url, ttl_s=0.0)
        assert status.nowait() is None  # no answer yet: the probe asks in its own thread
        assert status() is True and status.status()["storing"] is True
        assert status.nowait() is True  # then at once, from the event loop
        health.failed(RuntimeError("Cannot reserve 1.00 MiB, not enough space. (NOT_ENOUGH_SPACE)"))
        deadline = time.monotonic() + 10  # a probe keeps the last answer while a refresh runs
        while status() and time.monotonic() < deadline:
            time.sleep(0.05)
        report = probe_report({"history_store": status})
        assert report["ok"] is False
        assert "NOT_ENOUGH_SPACE" in report["reasons"]["history_store"]
        doc = status.status()
        assert (
            doc["storing"] is False
            and doc["failing_since_ms"]
            and "free disk space" in doc["reason"]
        )
    finally:
        server.shutdown()


def test_processors_that_do_not_answer_count_as_not_storing_with_the_reason() -> None:
    status = ProcessorsStatus(f"http://127.0.0.1:{free_port()}", ttl_s=0.0, timeout_s=0.5)
    started = time.monotonic()
    assert status() is False
    assert time.monotonic() - started < 2.0  # a probe waits at most about the timeout
    doc = status.status()
    assert doc["storing"] is False and doc["failing_since_ms"]
    assert "the processors do not answer" in doc["reason"] and "/history-status" in doc["reason"]
