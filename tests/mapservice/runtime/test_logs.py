"""Logs: in JSON mode every line, the libraries' included, is one JSON object with the component."""

from __future__ import annotations

import io
import json
import logging
import sys

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
    import httpx
    from fastapi import FastAPI

    from mapservice.local.embedded import free_port
    from mapservice.settings import Settings
    from tests.mapservice.sql.serving import ServedApi

    configure("INFO", "json", "api")
    app = FastAPI()
    app.get("/ping")(lambda: {"ok": True})
    with ServedApi(app, Settings(api_host="127.0.0.1", api_port=free_port())) as served:
        assert httpx.get(f"{served.url}/ping").status_code == 200
    out = [json.loads(line) for line in capfd.readouterr().err.splitlines() if line.startswith("{")]
    requests = [line for line in out if line.get("event") == "request"]
    assert requests and requests[0]["path"] == "/ping" and requests[0]["status"] == 200
    assert all(line["component"] == "api" for line in out)


SECRET = "s3cr3t-Pa55"
# Names that carry a secret, as clients spell them (any case, percent-encoded or not).
SECRET_PARAMS = ["password", "PASSWORD", "pass%77ord", "key", "api_key", "token", "access_token"]


@pytest.mark.parametrize("fmt", ["json", "console"])
def test_no_secret_in_a_url_reaches_the_api_access_log(capfd, tmp_path, fmt) -> None:
    """An analyst's `?password=` (and any other secret-named parameter) on the API's
    /clickhouse, served as `serve` serves it: the access log has the request, not the
    secret, in both formats."""
    import httpx
    from fastapi import FastAPI

    from mapservice.api.app import SQL_PATH, PathPrefix
    from mapservice.local.embedded import free_port
    from mapservice.settings import Settings
    from mapservice.sql.chdb_engine import ChdbEngine
    from mapservice.sql.http_protocol import SqlUser, clickhouse_http_app
    from tests.mapservice.sql.serving import ServedApi

    configure("INFO", fmt, "api")
    port = free_port()
    engine = ChdbEngine(tmp_path / "ch")
    app = FastAPI()
    app.add_middleware(
        PathPrefix,
        prefix=SQL_PATH,
        target=clickhouse_http_app(engine, [SqlUser("analyst", SECRET, read_only=True)]),
    )
    try:
        with ServedApi(app, Settings(api_host="127.0.0.1", api_port=port)) as served:
            base = f"{served.url}{SQL_PATH}/"
            reply = httpx.get(f"{base}?user=analyst&password={SECRET}&query=SELECT%201")
            assert reply.text == "1\n"
            for name in SECRET_PARAMS:
                httpx.get(f"{base}?user=analyst&{name}={SECRET}&query=SELECT%202")
    finally:
        engine.close()
    err = capfd.readouterr().err
    assert "SELECT%201" in err and "[redacted]" in err
    assert SECRET not in err


def test_no_secret_in_a_url_reaches_any_logger_path(capsys) -> None:
    """The other ways a URL reaches a line: a structlog field, a library's message (httpx
    logs each request's URL), its arguments, an exception's text."""
    import structlog

    configure("INFO", "json", "api")
    url = f"http://ch:8123/?user=svc&password={SECRET}&query=SELECT+1"
    structlog.get_logger("x").info("calling", url=url, nested={"urls": [url]})
    logging.getLogger("httpx").info(f'HTTP Request: POST {url} "HTTP/1.1 200 OK"')
    logging.getLogger("clickhouse_connect").warning("retrying %s", url)
    try:
        raise ConnectionError(f"unreachable: {url}")
    except ConnectionError:
        logging.getLogger("uvicorn.error").exception("request failed")
        structlog.get_logger("y").exception("request failed")
    out = capsys.readouterr().err
    assert len(lines_of(out)) == 5 and out.count("password=[redacted]") >= 6
    assert SECRET not in out and "query=SELECT+1" in out


def lines_of(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def test_a_logger_cached_while_stderr_was_redirected_writes_to_the_stderr_of_now(
    monkeypatch,
) -> None:
    """Loggers are cached on first use; one first used under a redirection that has since
    ended (a test's capture, a progress display) must not write to the closed stream."""
    then = io.StringIO()
    monkeypatch.setattr(sys, "stderr", then)
    configure("INFO", "json", "api")
    logger = structlog.get_logger("cached-under-redirection")
    logger.info("first")
    then.close()
    now = io.StringIO()
    monkeypatch.setattr(sys, "stderr", now)
    logger.info("second")
    assert json.loads(now.getvalue())["event"] == "second"
