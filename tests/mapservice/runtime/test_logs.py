"""Logs: in JSON mode every line, the libraries' included, is one JSON object with the component."""

from __future__ import annotations

import json
import logging

import pytest
import structlog

from mapservice.runtime.logs import configure


@pytest.fixture(autouse=True)
def restore_logging():
    """configure() is process-wide: put structlog and the root logger back after each test."""
    saved_config = structlog.get_config()
    root = logging.getLogger()
    saved = (root.handlers[:], root.level)
    libs = {
        n: (logging.getLogger(n).handlers[:], logging.getLogger(n).propagate)
        for n in ("uvicorn", "uvicorn.error", "uvicorn.access", "faust", "aiokafka", "mode")
    }
    yield
    structlog.configure(**saved_config)
    structlog.contextvars.clear_contextvars()
    root.handlers[:], root.level = saved
    for name, (handlers, propagate) in libs.items():
        logging.getLogger(name).handlers[:] = handlers
        logging.getLogger(name).propagate = propagate


def lines(capsys) -> list[dict]:
    return [json.loads(line) for line in capsys.readouterr().err.splitlines() if line.strip()]


def test_library_loggers_become_json_lines(capsys) -> None:
    """A stdlib logger (as aiokafka's) writes JSON with component, level, logger and the formatted message."""
    configure("INFO", "json", "processors")
    logging.getLogger("aiokafka.consumer").warning("lost partition %s", 3)
    (line,) = lines(capsys)
    assert line["component"] == "processors"
    assert (line["level"], line["logger"], line["event"]) == (
        "warning",
        "aiokafka.consumer",
        "lost partition 3",
    )
    assert line["timestamp"].endswith("Z")


def test_structlog_and_stdlib_share_one_format(capsys) -> None:
    """The service's own structlog lines are JSON too, with the same keys."""
    configure("INFO", "json", "gateway")
    structlog.get_logger("x").info("connected", broker="mqtt://h")
    (line,) = lines(capsys)
    assert (line["component"], line["level"], line["event"], line["broker"]) == (
        "gateway",
        "info",
        "connected",
        "mqtt://h",
    )


def test_uvicorn_access_log_is_structured(capsys) -> None:
    """A uvicorn access record becomes a 'request' line with client, method, path, HTTP version and status."""
    configure("INFO", "json", "api")
    logging.getLogger("uvicorn.access").info(
        '%s - "%s %s HTTP/%s" %d', "127.0.0.1:5000", "GET", "/api/v1/map", "1.1", 200
    )
    (line,) = lines(capsys)
    assert line["event"] == "request"
    assert (line["client"], line["method"], line["path"], line["http_version"], line["status"]) == (
        "127.0.0.1:5000",
        "GET",
        "/api/v1/map",
        "1.1",
        200,
    )


def test_handlers_libraries_install_are_replaced(capsys) -> None:
    """uvicorn's own handler is dropped, so its lines are not written twice or in plain text."""
    logging.getLogger("uvicorn.error").addHandler(logging.StreamHandler())
    configure("INFO", "json", "api")
    logging.getLogger("uvicorn.error").info("Started server process")
    (line,) = lines(capsys)
    assert line["event"] == "Started server process"


def test_below_the_level_nothing_is_written(capsys) -> None:
    """With level WARNING, a library's info line is not written."""
    configure("WARNING", "json", "api")
    logging.getLogger("faust").info("chatty")
    assert lines(capsys) == []


def test_the_api_server_writes_a_json_access_log(capfd) -> None:
    """The API's uvicorn (as `serve` configures it) writes one JSON 'request' line per request."""
    import socket
    import threading
    import time

    import httpx
    import uvicorn
    from fastapi import FastAPI
    from mapservice.api.composition import api_server_config

    from mapservice.settings import Settings

    configure("INFO", "json", "api")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    app = FastAPI()
    app.get("/ping")(lambda: {"ok": True})
    server = uvicorn.Server(api_server_config(app, Settings(api_host="127.0.0.1", api_port=port)))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 10
        while not server.started and time.monotonic() < deadline:
            time.sleep(0.05)
        assert httpx.get(f"http://127.0.0.1:{port}/ping").status_code == 200
    finally:
        server.should_exit = True
        thread.join(10)
    out = [json.loads(line) for line in capfd.readouterr().err.splitlines() if line.startswith("{")]
    requests = [line for line in out if line.get("event") == "request"]
    assert requests and requests[0]["path"] == "/ping" and requests[0]["status"] == 200
    assert all(line["component"] == "api" for line in out)
