"""One contract for every SqlEngine: ChdbEngine (this process's chDB) and ServerEngine (a
ClickHouse server's HTTP interface; here the chDB one, served from this process)."""

from __future__ import annotations

import pytest

from mapservice.sql.chdb_engine import ChdbEngine
from mapservice.sql.engine import READONLY, SqlError, SqlRequest
from mapservice.sql.http_protocol import SqlUser, clickhouse_http_app
from mapservice.sql.read_only import ReadOnlyLimits
from mapservice.sql.server_engine import ServerEngine

from .serving import ServedApp

LIMITS = ReadOnlyLimits(max_execution_time_s=5, max_result_rows=100).settings()


@pytest.fixture(scope="module")
def chdb_engine(tmp_path_factory):
    engine = ChdbEngine(tmp_path_factory.mktemp("sql") / "ch", read_only_settings=LIMITS)
    engine.execute(SqlRequest("CREATE DATABASE IF NOT EXISTS contract"))
    engine.execute(
        SqlRequest(
            "CREATE TABLE IF NOT EXISTS contract.t (n UInt32, s String) "
            "ENGINE = MergeTree ORDER BY n"
        )
    )
    yield engine
    engine.close()


@pytest.fixture(scope="module")
def server_engine(chdb_engine):
    app = clickhouse_http_app(chdb_engine, [SqlUser("writer", "pw", read_only=False)])
    with ServedApp(app) as served:
        engine = ServerEngine(served.url, "writer", "pw", read_only_settings=LIMITS)
        yield engine
        engine.close()


@pytest.fixture(params=["chdb", "server"])
def engine(request):
    engine = request.getfixturevalue(f"{request.param}_engine")
    engine.execute(SqlRequest("TRUNCATE TABLE contract.t"))
    return engine


def rows(engine, sql: str, **kw) -> list[str]:
    return engine.execute(SqlRequest(sql, default_format="TSV", **kw)).body.decode().splitlines()


def test_executes_in_the_default_format_or_the_statements_own(engine) -> None:
    """No FORMAT clause: the request's default format; a FORMAT clause wins."""
    assert (
        engine.execute(SqlRequest("SELECT 1 AS x", default_format="CSVWithNames")).body
        == b'"x"\n1\n'
    )
    result = engine.execute(SqlRequest("SELECT 2 AS x FORMAT JSONEachRow"))
    assert result.body == b'{"x":2}\n' and result.format == "JSONEachRow"


def test_binds_parameters_by_name_never_into_the_text(engine) -> None:
    """{name:Type} placeholders take request values as data, quotes and all."""
    assert rows(engine, "SELECT {s:String}, {n:UInt8} + 1", params={"s": "a'b", "n": "41"}) == [
        "a\\'b\t42"
    ]


def test_binds_parameters_far_larger_than_a_url(engine) -> None:
    """A 2,000-value array parameter (70 KB; the server engine sends it as multipart)."""
    values = "[" + ",".join(f"'{n:032x}'" for n in range(2000)) + "]"
    assert rows(engine, "SELECT length({v:Array(String)})", params={"v": values}) == ["2000"]


def test_inserts_rows_in_a_format_and_reads_them_back(engine) -> None:
    """insert(target, fmt, data) stores the rows."""
    engine.insert("contract.t (n, s)", "TSV", b"1\tone\n2\ttwo\n", SqlRequest(""))
    assert rows(engine, "SELECT n, s FROM contract.t ORDER BY n") == ["1\tone", "2\ttwo"]


def test_uses_the_requested_database(engine) -> None:
    """`database` is the unqualified names' database."""
    assert rows(engine, "SELECT currentDatabase()", database="contract") == ["contract"]


def test_settings_last_one_request(engine) -> None:
    """A request's settings apply to it only, never to the next request."""
    assert rows(engine, "SELECT getSetting('max_threads') = 3", settings={"max_threads": "3"}) == [
        "1"
    ]
    assert rows(engine, "SELECT getSetting('max_threads') = 3") == ["0"]


def test_errors_carry_clickhouse_codes(engine) -> None:
    """A missing table is code 60 (404 over HTTP); bad syntax 62 (400)."""
    with pytest.raises(SqlError) as missing:
        engine.execute(SqlRequest("SELECT * FROM contract.nope"))
    assert missing.value.code == 60 and missing.value.http_status == 404
    with pytest.raises(SqlError) as syntax:
        engine.execute(SqlRequest("SELEC 1"))
    assert syntax.value.code == 62 and syntax.value.http_status == 400


def test_read_only_requests_cannot_write_or_lift_limits(engine) -> None:
    """read_only: writes, DDL and setting changes are refused by the engine itself."""
    for sql in (
        "INSERT INTO contract.t VALUES (9, 'x')",
        "DROP TABLE contract.t",
        "SELECT 1 SETTINGS max_execution_time = 1000",
    ):
        with pytest.raises(SqlError) as refused:
            engine.execute(SqlRequest(sql, read_only=True))
        assert refused.value.code == READONLY, sql
    with pytest.raises(SqlError):
        engine.insert("contract.t (n, s)", "TSV", b"3\tthree\n", SqlRequest("", read_only=True))
    assert rows(engine, "SELECT count() FROM contract.t", read_only=True) == ["0"]


def test_read_only_requests_run_under_the_limits(engine) -> None:
    """A read-only result beyond max_result_rows is an error, not a truncated answer."""
    with pytest.raises(SqlError) as too_many:
        engine.execute(SqlRequest("SELECT number FROM system.numbers LIMIT 1000", read_only=True))
    assert too_many.value.code == 396  # TOO_MANY_ROWS_OR_BYTES


def test_ping(engine) -> None:
    """ping() is True while the engine answers."""
    assert engine.ping() is True


def test_a_server_address_is_not_a_chdb_directory() -> None:
    """ChdbEngine refuses an http:// DSN instead of creating a directory named after it."""
    with pytest.raises(ValueError, match="not a chDB directory"):
        ChdbEngine("http://127.0.0.1:8123")
