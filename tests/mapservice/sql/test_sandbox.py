"""The analysts' sandbox, tested from the engine's own catalogues rather than a list of
attacks: every setting of `system.settings` through every channel that can carry one,
and every function of `system.functions` and table function of `system.table_functions`,
called directly and through wrappers, with a canary file and a canary TCP listener that
must never be reached. The counts are printed (`-s`) and recorded in the test's report.

The chDB engine here is the one the API and `mapservice clickhouse-server` run;
test_sandbox_server.py runs the known settings attacks on the ServerEngine path."""

from __future__ import annotations

import socket
import threading
from dataclasses import replace

import pytest
from starlette.testclient import TestClient

from mapservice.sql.allow_list import BY_NAME_CALLERS, catalogue
from mapservice.sql.chdb_engine import ChdbEngine
from mapservice.sql.engine import SqlError, SqlRequest
from mapservice.sql.http_protocol import PROTOCOL_PARAMS, SqlUser, clickhouse_http_app
from mapservice.sql.read_only import ReadOnlyLimits, check_read_only
from mapservice.sql.settings_policy import HARMLESS, PROTOCOL_HEADERS, UNSET_LIMITS

CANARY = "canary-secret-that-must-never-be-read"
LIMITS = ReadOnlyLimits(max_result_rows=1000, max_execution_time_s=5).settings()
AUTH = ("analyst", "a-pw")
CHUNKS = 4


class CanaryListener:
    """A TCP listener on 127.0.0.1 that counts the connections it gets."""

    def __init__(self) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.connections = 0
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            self.connections += 1
            conn.close()

    def close(self) -> None:
        self.sock.close()


@pytest.fixture(scope="module")
def sandbox(tmp_path_factory):
    root = tmp_path_factory.mktemp("sandbox")
    secret = root / "secrets" / "admin-token"
    secret.parent.mkdir()
    secret.write_text(CANARY + "\n")
    engine = ChdbEngine(root / "clickhouse", read_only_settings=LIMITS)
    engine.execute(SqlRequest("CREATE DATABASE IF NOT EXISTS mapservice"))
    engine.execute(
        SqlRequest(
            "CREATE TABLE IF NOT EXISTS mapservice.poses (robot_id String, x Float64) "
            "ENGINE = MergeTree ORDER BY robot_id"
        )
    )
    engine.execute(SqlRequest("INSERT INTO mapservice.poses VALUES ('a', 1), ('b', 2)"))
    listener = CanaryListener()
    app = clickhouse_http_app(
        engine, [SqlUser(*AUTH, read_only=True)], read_only_database="mapservice"
    )
    with TestClient(app) as client:
        yield engine, client, secret, listener
    listener.close()
    engine.close()


def rows(engine, sql: str) -> list[list[str]]:
    out = engine.execute(SqlRequest(sql, default_format="TSV")).body.decode()
    return [line.split("\t") for line in out.splitlines()]


def chunk(items: list, index: int) -> list:
    return items[index::CHUNKS]


# --- settings x channels ---------------------------------------------------------------


def accepted(name: str) -> bool:
    return name in HARMLESS or name in LIMITS or name in UNSET_LIMITS


def value_for(name: str, default: str) -> str:
    """A value the engine takes: the limit in force for a limit, else the default (a
    harmful value is not needed: a refusal is by name)."""
    return LIMITS.get(name) or ("1000" if name in UNSET_LIMITS else default)


def literal(value: str) -> str:
    return "'" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"


CHANNELS = ("URL parameter", "form field", "X-ClickHouse header", "SETTINGS", "SET", "parameter")


def send(client, channel: str, name: str, value: str):
    if channel == "URL parameter":
        return client.post("/", params={name: value}, content=b"SELECT 1", auth=AUTH)
    if channel == "form field":
        return client.post("/", files={"query": (None, "SELECT 1"), name: (None, value)}, auth=AUTH)
    if channel == "X-ClickHouse header":
        return client.post(
            "/", headers={f"X-ClickHouse-{name}": value}, content=b"SELECT 1", auth=AUTH
        )
    if channel == "SETTINGS":
        sql = f"SELECT 1 FROM (SELECT 1 SETTINGS {name} = {literal(value)})"
        return client.post("/", content=sql.encode(), auth=AUTH)
    if channel == "SET":
        return client.post("/", content=f"SET {name} = {literal(value)}".encode(), auth=AUTH)
    sql = f"WITH x AS (SELECT 1 SETTINGS {name} = {{v:String}}) SELECT * FROM x"
    return client.post("/", params={"param_v": value}, content=sql.encode(), auth=AUTH)


@pytest.mark.parametrize("index", range(CHUNKS))
@pytest.mark.parametrize("channel", CHANNELS)
def test_every_setting_through_every_channel_is_refused_unless_allowed(
    sandbox, channel, index
) -> None:
    """Each of system.settings' settings, sent by `channel`: a 4xx naming it, unless it is
    on the policy's list (then the statement runs; a header is never a setting here, and a
    protocol parameter is read by the HTTP interface, never applied)."""
    engine, client, _, _ = sandbox
    settings = chunk(rows(engine, "SELECT name, default FROM system.settings ORDER BY name"), index)
    refused, allowed, wrong = 0, 0, []
    for name, default in settings:
        value = value_for(name, default)
        reply = send(client, channel, name, value)
        if channel == "X-ClickHouse header":
            should_pass = f"x-clickhouse-{name.lower()}" in PROTOCOL_HEADERS
        elif channel in ("URL parameter", "form field"):
            should_pass = accepted(name) or name in PROTOCOL_PARAMS
        else:
            should_pass = accepted(name)
        if should_pass:
            allowed += 1
            if reply.status_code != 200:
                wrong.append((name, "refused", reply.status_code, reply.text[:200]))
        else:
            refused += 1
            if not (400 <= reply.status_code < 500 and name.lower() in reply.text.lower()):
                wrong.append((name, "passed", reply.status_code, reply.text[:200]))
    print(f"settings via {channel} [{index}]: {refused} refused, {allowed} accepted")
    assert not wrong, wrong[:10]
    assert refused + allowed == len(settings) > 300


def test_a_limit_is_only_ever_tightened(sandbox) -> None:
    """0 (unlimited), a larger value or a word: refused by every channel; a smaller value
    applies (max_result_rows = 2 stops a 3-row result)."""
    _, client, _, _ = sandbox
    for name, limit in LIMITS.items():
        for value in ("0", str(int(limit) * 10) if limit.isdigit() else "break", "-1", "x"):
            reply = client.post("/", params={name: value}, content=b"SELECT 1", auth=AUTH)
            assert reply.status_code == 403 and name in reply.text, (name, value, reply.text)
    tight = client.post(
        "/", params={"max_result_rows": "2"}, content=b"SELECT * FROM numbers(3)", auth=AUTH
    )
    assert tight.status_code == 500 and "396" in tight.headers["X-ClickHouse-Exception-Code"]
    loose = client.post("/", content=b"SELECT * FROM numbers(3)", auth=AUTH)
    assert loose.status_code == 200 and loose.text == "0\n1\n2\n"


def test_an_engine_called_directly_applies_readonly_and_the_limits_last(sandbox) -> None:
    """Whatever a read-only request carries, the engine sets it before the limits and
    readonly = 1, and refuses a setting outside the policy itself."""
    engine = sandbox[0]
    for settings in ({"readonly": "0"}, {"max_threads": "1", "readonly": "2"}):
        request = SqlRequest(
            "SELECT getSetting('readonly'), getSetting('max_threads')",
            settings=settings,
            read_only=True,
            default_format="TSVRaw",
        )
        assert engine.execute(request).body == b"1\t1\n"
    with pytest.raises(SqlError, match="additional_table_filters"):
        engine.execute(
            SqlRequest("SELECT 1", settings={"additional_table_filters": "{}"}, read_only=True)
        )


# --- functions x wrappers --------------------------------------------------------------


def run_as_analyst(engine, sql: str) -> str:
    """What the analyst's /clickhouse does with `sql`: the check, then the checked
    statement on a read-only handle; the reply's text or the error's."""
    request = SqlRequest(sql, database="mapservice", read_only=True, analyst=True)
    try:
        checked = check_read_only(engine, request, "mapservice", LIMITS)
        return engine.execute(replace(request, sql=checked)).body.decode("utf-8", "replace")
    except SqlError as exc:
        return str(exc)


def function_cases(name: str, aggregate: bool, refused: bool, secret: str, url: str):
    """`name` called with the canary file and the canary listener's address, directly; a
    function the allow-list refuses also through a CTE, a lambda, a subquery in IN,
    a JOIN, its combinators and the functions that call an aggregate by name (an allowed
    one computes on its arguments wherever it is called)."""
    for arg in (secret, url):
        yield f"SELECT {name}({arg})"
    if not refused:
        return
    call = f"{name}({secret})"
    yield f"WITH t AS (SELECT {call} AS v) SELECT * FROM t"
    yield f"SELECT arrayMap(x -> {name}({url}), [1])"
    yield f"SELECT 1 WHERE 1 IN (SELECT {call})"
    yield f"SELECT * FROM numbers(1) AS a JOIN (SELECT {name}({url}) AS v) AS b ON 1"
    yield f"SELECT * FROM view(SELECT {call})"
    if aggregate:
        yield f"SELECT {name}If({secret}, 1)"
        yield f"SELECT {name}State({url})"
    for caller in sorted(BY_NAME_CALLERS):
        array = "[(1, 1)], " if caller == "arrayReduceInRanges" else ""
        args = f"[{secret}]" if caller != "initializeAggregation" else secret
        yield f"SELECT {caller}('{name}', {array}{args})"


def table_function_cases(name: str, secret: str, url: str):
    for arg in (secret, url):
        source = f"{name}({arg}, 'LineAsString')"
        yield f"SELECT * FROM {source}"
        yield f"SELECT * FROM (SELECT * FROM {source})"
        yield f"WITH t AS (SELECT * FROM {source}) SELECT * FROM t"
        yield f"SELECT 1 WHERE 1 IN (SELECT * FROM {source})"
        yield f"SELECT * FROM view(SELECT * FROM {source})"
    yield f"SELECT * FROM {name}()"


@pytest.mark.parametrize("index", range(CHUNKS))
def test_no_function_or_table_function_reaches_a_file_or_the_network(sandbox, index) -> None:
    """Every function and table function of the engine's catalogues, with the canary
    file's path and the canary listener's URL as arguments: the canary never appears in
    a reply and the listener gets no connection."""
    engine, _, secret_file, listener = sandbox
    secret = f"'{secret_file}'"
    url = f"'http://127.0.0.1:{listener.port}/canary'"
    functions = chunk(
        rows(engine, "SELECT name, is_aggregate FROM system.functions ORDER BY name"), index
    )
    tables = chunk(rows(engine, "SELECT name FROM system.table_functions ORDER BY name"), index)
    tried, statements, ran = 0, 0, 0
    for name, aggregate in functions:
        refused_alone = not catalogue().allows(name)
        for sql in function_cases(name, aggregate == "1", refused_alone, secret, url):
            reply = run_as_analyst(engine, sql)
            statements += 1
            ran += not reply.startswith("Code:")
            assert CANARY not in reply, sql
        tried += 1
    for (name,) in tables:
        for sql in table_function_cases(name, secret, url):
            reply = run_as_analyst(engine, sql)
            statements += 1
            ran += not reply.startswith("Code:")
            assert CANARY not in reply, sql
        tried += 1
    assert listener.connections == 0
    assert secret_file.read_text() == CANARY + "\n"
    print(
        f"functions [{index}]: {tried} functions and table functions tried in "
        f"{statements} statements ({ran} ran), canary untouched"
    )
    assert tried > 400


def test_the_functions_that_call_another_by_name_are_known(sandbox) -> None:
    """system.functions documents which functions take an aggregate function's name: the
    allow-list checks that name for each of them."""
    engine = sandbox[0]
    documented = {
        name
        for (name,) in rows(
            engine,
            "SELECT name FROM system.functions WHERE arguments ILIKE '%name of%function%'",
        )
    }
    assert documented == BY_NAME_CALLERS


@pytest.mark.parametrize("caller", sorted(BY_NAME_CALLERS))
def test_a_function_named_in_a_string_is_checked_like_a_call(sandbox, caller) -> None:
    """arrayReduce('flameGraph', ...) and the like: refused naming the function; an allowed
    aggregate (with parameters and combinators) still works."""
    engine = sandbox[0]
    array = "[(1, 1)], " if caller == "arrayReduceInRanges" else ""
    arg = "[1]" if caller != "initializeAggregation" else "1"
    for name in ("flameGraph", "FLAMEGRAPH", "flameGraphIf", "flameGraph(1)"):
        reply = run_as_analyst(engine, f"SELECT {caller}('{name}', {array}{arg})")
        assert "not allowed" in reply and "flameGraph".lower() in reply.lower(), reply
    reply = run_as_analyst(engine, f"SELECT {caller}(concat('flame', 'Graph'), {array}{arg})")
    assert "string literal" in reply, reply
    for name in ("max", "sumIf", "quantile(0.5)"):
        args = f"{arg}, 1" if name == "sumIf" and caller == "initializeAggregation" else arg
        if name == "sumIf" and caller != "initializeAggregation":
            args = f"{arg}, [1]"
        reply = run_as_analyst(engine, f"SELECT {caller}('{name}', {array}{args})")
        assert not reply.startswith("Code: 497"), reply
