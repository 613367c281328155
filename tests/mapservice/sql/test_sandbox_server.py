"""The analysts' door as `make up` wires it: the API's /clickhouse (the HTTP interface over
a ServerEngine) forwards to `mapservice clickhouse-server` (the HTTP interface over
chDB), which holds the service's read-write user and the analyst. The settings attacks
that lifted read-only and the limits through that path are refused by the front, and,
sent straight to the server as the analyst, by the server too.

What this does not cover: a real ClickHouse server (none can run here). There the
analysts' user of infra/k8s/platform/clickhouse.yaml holds readonly and the limits as
constant constraints of its profile; the ServerEngine sends the same requests to it."""

from __future__ import annotations

import pytest
from starlette.testclient import TestClient

from mapservice.sql.chdb_engine import ChdbEngine
from mapservice.sql.engine import SqlRequest
from mapservice.sql.http_protocol import SqlUser, clickhouse_http_app
from mapservice.sql.read_only import ReadOnlyLimits
from mapservice.sql.server_engine import ServerEngine

from .serving import ServedApp

CANARY = "admin-token-that-must-not-leak"
LIMITS = ReadOnlyLimits(max_result_rows=1000, max_execution_time_s=5).settings()
ANALYST = ("analyst", "a-pw")


class RecordingEngine(ChdbEngine):
    """The server's chDB engine, noting whether each statement came read-only."""

    seen: list[tuple[str, bool]]

    def execute(self, request: SqlRequest):
        self.seen.append((request.sql, request.read_only))
        return super().execute(request)


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    root = tmp_path_factory.mktemp("apart")
    secret = root / "secrets" / "admin-token"
    secret.parent.mkdir()
    secret.write_text(CANARY + "\n")
    engine = RecordingEngine(root / "clickhouse", read_only_settings=LIMITS)
    engine.seen = []
    engine.execute(SqlRequest("CREATE DATABASE IF NOT EXISTS mapservice"))
    engine.execute(
        SqlRequest(
            "CREATE TABLE IF NOT EXISTS mapservice.poses (robot_id String, x Float64) "
            "ENGINE = MergeTree ORDER BY robot_id"
        )
    )
    server = clickhouse_http_app(
        engine,
        [SqlUser(*ANALYST, read_only=True), SqlUser("service", "s-pw", read_only=False)],
        read_only_database="mapservice",
    )
    with ServedApp(server) as served:
        forward = ServerEngine(
            served.url, "service", "s-pw", read_only_settings=LIMITS, analyst_auth=ANALYST
        )
        front = clickhouse_http_app(
            forward, [SqlUser(*ANALYST, read_only=True)], read_only_database="mapservice"
        )
        with TestClient(front) as api, TestClient(server) as direct:
            yield api, direct, engine, secret
        forward.close()
    engine.close()


def attacks(secret) -> list[tuple[str, dict[str, str], str]]:
    """(setting named in the refusal, URL parameters, statement): settings attacks seen on the analysts' door."""
    filters = f"{{'system.one':'toInt64(file(\\'{secret}\\'))=1'}}"
    return [
        (
            "additional_table_filters",
            {"additional_table_filters": filters},
            "SELECT * FROM system.one",
        ),
        ("format_template_row", {"format_template_row": str(secret)}, "SELECT 1 FORMAT Template"),
        ("readonly", {"readonly": "0"}, "SELECT 1"),
        ("readonly", {"readonly": "2"}, "SELECT 1"),
        ("max_execution_time", {"max_execution_time": "60"}, "SELECT 1"),
        ("max_threads", {"max_threads": "4"}, "SELECT 1"),
        ("max_memory_usage", {"max_memory_usage": "0"}, "SELECT 1"),
        ("max_result_rows", {"max_result_rows": "0"}, "SELECT 1"),
        ("result_overflow_mode", {"result_overflow_mode": "break"}, "SELECT 1"),
    ]


@pytest.mark.parametrize("door", ["api", "server"])
@pytest.mark.parametrize("channel", ["URL parameter", "form field", "SETTINGS"])
def test_the_settings_attacks_are_refused_on_both_doors(stack, door, channel) -> None:
    """Through the API (ServerEngine) and straight at the server as the analyst: 403
    naming the setting, the canary never in a reply."""
    api, direct, _, secret = stack
    client = api if door == "api" else direct
    for name, params, sql in attacks(secret):
        if channel == "URL parameter":
            reply = client.post("/", params=params, content=sql.encode(), auth=ANALYST)
        elif channel == "form field":
            fields = {"query": (None, sql), **{k: (None, v) for k, v in params.items()}}
            reply = client.post("/", files=fields, auth=ANALYST)
        else:
            clause = ", ".join(
                f"{k} = '{v.replace(chr(92), chr(92) * 2).replace(chr(39), chr(92) + chr(39))}'"
                for k, v in params.items()
            )
            reply = client.post("/", content=f"{sql} SETTINGS {clause}".encode(), auth=ANALYST)
        assert 400 <= reply.status_code < 500 and name in reply.text, (name, reply.text)
        assert CANARY not in reply.text


def test_an_analyst_statement_reaches_the_server_as_the_analyst(stack) -> None:
    """The API forwards the analyst's statement with the analyst's own credential: the
    server runs it as its read-only user (under its own check), not as the service."""
    api, _, engine, _ = stack
    engine.seen.clear()
    reply = api.post("/", content=b"SELECT 4242", auth=ANALYST)
    assert reply.status_code == 200 and reply.text == "4242\n"
    ran = [read_only for sql, read_only in engine.seen if sql.strip() == "SELECT 4242"]
    assert ran == [True], engine.seen


def test_tighter_limits_and_output_settings_still_work_through_the_api(stack) -> None:
    """What clients send that is harmless goes through both doors."""
    api, _, _, _ = stack
    reply = api.post(
        "/",
        params={"max_result_rows": "2", "output_format_json_quote_64bit_integers": "0"},
        content=b"SELECT toUInt64(7) AS n FORMAT JSONEachRow",
        auth=ANALYST,
    )
    assert reply.status_code == 200 and reply.text == '{"n":7}\n', reply.text
    too_many = api.post(
        "/", params={"max_result_rows": "2"}, content=b"SELECT * FROM numbers(3)", auth=ANALYST
    )
    assert too_many.status_code == 500 and "TOO_MANY_ROWS" in too_many.text


def test_the_api_forwards_with_the_analysts_own_server_credential(tmp_path, monkeypatch) -> None:
    """MAPSERVICE_CLICKHOUSE_ANALYST_USERNAME/PASSWORD when set; in local mode without them
    the analyst's own credential (which `mapservice clickhouse-server` serves read-only);
    in production without them the service's user (None)."""
    from mapservice.settings import Settings
    from mapservice.sql.apps import analyst_server_credential

    analyst = SqlUser("analyst", "a-pw", read_only=True)
    monkeypatch.setenv("MAPSERVICE_CLICKHOUSE_ANALYST_USERNAME", "mapservice_analyst")
    monkeypatch.setenv("MAPSERVICE_CLICKHOUSE_ANALYST_PASSWORD", "ch-pw")
    configured = Settings(data_dir=tmp_path, clickhouse_dsn="http://ch:8123")
    assert analyst_server_credential(configured, analyst) == ("mapservice_analyst", "ch-pw")
    monkeypatch.delenv("MAPSERVICE_CLICKHOUSE_ANALYST_USERNAME")
    local = Settings(data_dir=tmp_path, clickhouse_dsn="http://127.0.0.1:8123", mode="local")
    assert analyst_server_credential(local, analyst) == ("analyst", "a-pw")
    production = local.model_copy(update={"mode": "production"})
    assert analyst_server_credential(production, analyst) is None
