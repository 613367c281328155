"""The attack suite: an outsider with the analyst's password tries to read the service's
secrets, the process's environment and the machine's files, or to reach the network,
through the analysts' /clickhouse (here: the same app over chDB, with a data dir holding
secrets). Every statement is refused with ClickHouse's ACCESS_DENIED (497) naming the
function or table, and the secret never appears in a reply.

tests/mapservice/sql/attacks_on_old_checker.py runs the same statements through the
checker before the allow-list: there they return the secret."""

from __future__ import annotations

import json
import re
from dataclasses import replace

import httpx
import pytest

from mapservice.sql.allow_list import ALLOWED_CATEGORIES, ALLOWED_TABLE_FUNCTIONS, catalogue
from mapservice.sql.chdb_engine import ChdbEngine
from mapservice.sql.engine import SqlError, SqlRequest
from mapservice.sql.http_protocol import SqlUser, clickhouse_http_app
from mapservice.sql.read_only import ReadOnlyLimits, check_read_only

from .attacks import ATTACKS
from .serving import ServedApp

MARKER = "admin-token-that-must-not-leak"
# What reads files or the network, or says what the server is: names as system.functions
# lists them (pure string functions of the URL, String and Hash categories, which only
# parse their argument, are not among them).
REACHES_OUT = re.compile(
    r"file|url|s3|hdfs|remote|mysql|postgres|exec|python|azure|gcs|redis|"
    r"mongo|sqlite|odbc|jdbc|input|dict|^ai[A-Z]|"
    r"region|setting|macro|host|user|certificate|header|server|zookeeper",
    re.IGNORECASE,
)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    data = tmp_path_factory.mktemp("attacked") / ".mapservice-data"
    (data / "secrets").mkdir(parents=True)
    (data / "secrets" / "admin-token").write_text(MARKER + "\n")
    (data / "secrets" / "robots.json").write_text('{"r1": "' + MARKER + '"}')
    return data


@pytest.fixture(scope="module")
def engine(data):
    engine = ChdbEngine(data / "clickhouse", read_only_settings=ReadOnlyLimits().settings())
    engine.execute(SqlRequest("CREATE DATABASE IF NOT EXISTS mapservice"))
    engine.execute(
        SqlRequest(
            "CREATE TABLE IF NOT EXISTS mapservice.poses (robot_id String, "
            "x Float64) ENGINE = MergeTree ORDER BY robot_id"
        )
    )
    engine.execute(SqlRequest("INSERT INTO mapservice.poses VALUES ('a', 1), ('a', 2), ('b', 5)"))
    yield engine
    engine.close()


@pytest.fixture(scope="module")
def url(engine):
    app = clickhouse_http_app(
        engine, [SqlUser("analyst", "a-pw", read_only=True)], read_only_database="mapservice"
    )
    with ServedApp(app) as served:
        yield served.url


def statement(template: str, data) -> str:
    return template.format(data=data, secret=data / "secrets" / "admin-token")


@pytest.mark.parametrize("name,template", ATTACKS, ids=[a[0] for a in ATTACKS])
def test_each_attack_is_refused_with_its_reason(url, data, name, template) -> None:
    """403, ACCESS_DENIED (or READONLY), the refused function or table named; no secret."""
    reply = httpx.post(url, content=statement(template, data).encode(), auth=("analyst", "a-pw"))
    assert reply.status_code == 403, reply.text
    assert reply.headers["X-ClickHouse-Exception-Code"] == "497", reply.text
    assert re.search(
        r"(Function|Table function|Table|Database) \S+ is not (allowed|readable)"
        r"|APPLY column transformer is not allowed|Identifier .* has a line break"
        r"|SHOW \w+( \w+)? is not allowed",
        reply.text,
        re.DOTALL,
    ), reply.text
    assert MARKER not in reply.text


def refused(engine, sql: str) -> str:
    request = SqlRequest(sql, database="mapservice", read_only=True)
    with pytest.raises(SqlError) as caught:
        check_read_only(engine, request, "mapservice")
    if caught.value.code == 62 and "('x')" in sql:  # takes a subquery (viewIfPermitted)
        return refused(engine, sql.replace("('x')", "(SELECT 1 ELSE null('x UInt8'))"))
    assert caught.value.code == 497, str(caught.value)
    return str(caught.value)


def system_functions(engine) -> list[tuple[str, str, str]]:
    out = engine.execute(
        SqlRequest(
            "SELECT name, categories, alias_to FROM system.functions", default_format="TSVRaw"
        )
    ).body.decode()
    return [tuple(line.split("\t")) for line in out.splitlines()]


def test_every_function_that_reads_files_or_the_network_is_refused(engine) -> None:
    """Enumerated from system.functions at test time: each such function (and alias of
    one), in its own case, in capitals and nested in a lambda, is refused by name."""
    rows = system_functions(engine)
    category = {name: cats for name, cats, _ in rows}
    reaching = sorted(
        name
        for name, cats, alias_to in rows
        if REACHES_OUT.search(name)
        and not (
            {c.strip() for c in category.get(alias_to or name, cats).split(",")}
            & ALLOWED_CATEGORIES
        )
    )
    assert {
        "file",
        "filesystemAvailable",
        "aiGenerate",
        "dictGet",
        "getSetting",
        "hostName",
        "getServerSetting",
        "currentUser",
        "user",
    } <= set(reaching)
    for name in reaching:
        assert f"Function {name} is not allowed" in refused(engine, f"SELECT {name}('/etc/passwd')")
        upper = name.upper()
        if not catalogue().allows(upper):
            assert f"Function {upper} is not allowed" in refused(engine, f"SELECT {upper}('x')")
        assert f"Function {name} is not allowed" in refused(
            engine, f"SELECT arrayMap(p -> {name}(p), ['x'])"
        )


def test_every_table_function_but_the_listed_is_refused(engine) -> None:
    """All of system.table_functions but numbers/values/view and the like: file, url, s3,
    remote, mysql, executable, python, iceberg, ... in FROM and in a JOIN."""
    out = (
        engine.execute(
            SqlRequest("SELECT name FROM system.table_functions", default_format="TSVRaw")
        )
        .body.decode()
        .split()
    )
    others = [n for n in out if n.lower() not in ALLOWED_TABLE_FUNCTIONS]
    assert {
        "file",
        "url",
        "s3",
        "remote",
        "mysql",
        "postgresql",
        "executable",
        "python",
        "hdfs",
        "azureBlobStorage",
        "sqlite",
        "odbc",
        "jdbc",
        "input",
        "merge",
    } <= set(others)
    for name in others:
        assert f"Table function {name} is not allowed" in refused(
            engine, f"SELECT * FROM {name}('x')"
        )
        assert f"Table function {name} is not allowed" in refused(
            engine, f"SELECT * FROM numbers(1) AS n JOIN {name}('x') AS t ON 1"
        )


def test_every_function_off_the_list_is_refused(engine) -> None:
    """Allow-list, not deny-list: each system.functions name the list does not hold."""
    names = [name for name, _, _ in system_functions(engine) if not catalogue().allows(name)]
    assert len(names) > 100 and "file" in names
    for name in names:
        assert f"Function {name} is not allowed" in refused(engine, f"SELECT {name}()")


@pytest.mark.parametrize(
    "sql,expected",
    [
        (
            "SELECT robot_id, count(), sumIf(x, x > 1), avg(x) FROM poses GROUP BY robot_id ORDER BY robot_id",
            "a\t2\t2\t1.5\nb\t1\t5\t5\n",
        ),
        ("SELECT uniqMerge(s) FROM (SELECT uniqState(robot_id) AS s FROM mapservice.poses)", "2\n"),
        (
            "SELECT COUNT(), Sum(x), groupArrayOrNull(robot_id) IS NOT NULL FROM mapservice.poses",
            "3\t8\t1\n",
        ),
        (
            "WITH c AS (SELECT robot_id, x FROM mapservice.poses) "
            "SELECT arrayMap(v -> v * 2, groupArray(x)) FROM (SELECT x FROM c ORDER BY x)",
            "[2,4,10]\n",
        ),
        (
            "SELECT robot_id, first_value(x) OVER (PARTITION BY robot_id ORDER BY x) AS f FROM poses "
            "ORDER BY robot_id, x LIMIT 1",
            "a\t1\n",
        ),
        (
            "SELECT x::Int32, toStartOfHour(toDateTime('2026-01-01 10:20:00', 'UTC') + INTERVAL 1 HOUR), "
            "[1, 2][2], if(x > 1, 'y', 'n') FROM poses ORDER BY x LIMIT 1",
            "1\t2026-01-01 11:00:00\t2\tn\n",
        ),
        (
            "SELECT count() FROM system.columns WHERE database = 'mapservice' AND table = 'poses'",
            "2\n",
        ),
        ("SELECT count() > 1000 FROM system.functions", "1\n"),
        ("SELECT count() FROM numbers(10) WHERE number IN (SELECT 3)", "1\n"),
        ("SELECT ('a', 1.0) IN mapservice.poses", "1\n"),
        ("SHOW TABLES FROM mapservice", "poses\n"),
        ("show databases like 'mapservice'", "mapservice\n"),
        ("SHOW SETTINGS LIKE 'max_threads'", None),
        ("DESCRIBE TABLE mapservice.poses", None),
        ("SELECT version() != '', timezone() != ''", "1\t1\n"),
    ],
)
def test_what_analysts_do_is_allowed(url, sql, expected) -> None:
    """Aggregates with combinators, any case, CTEs, lambdas, windows, casts, intervals,
    the schema's system tables, SHOW and DESCRIBE: all allowed."""
    reply = httpx.post(url, content=sql.encode(), auth=("analyst", "a-pw"))
    assert reply.status_code == 200, reply.text
    if expected is not None:
        assert reply.text == expected


def test_the_database_parameter_cannot_leave_the_service_database(url) -> None:
    """`database=system` would make every unqualified name a system table: refused."""
    reply = httpx.post(
        url, params={"database": "system"}, content=b"SELECT * FROM users", auth=("analyst", "a-pw")
    )
    assert reply.status_code == 403 and "Database system is not readable" in reply.text


def test_the_check_is_on_the_statement_that_runs(engine) -> None:
    """What was checked is what runs: the formatted statement, not the raw text."""
    request = SqlRequest(
        "SELECT   1 /* file('/etc/passwd') */", database="mapservice", read_only=True
    )
    assert check_read_only(engine, request, "mapservice") == "SELECT 1"
    assert (
        check_read_only(engine, replace(request, sql="SELECT 'file(x)'"), "mapservice")
        == "SELECT 'file(x)'"
    )


def test_an_analyst_statement_runs_under_the_limits(url) -> None:
    """The read-only handle carries the limits (time, rows, memory, threads); analysts can
    see them in system.settings and cannot change them."""
    sql = (
        "SELECT name, value FROM system.settings WHERE name IN ('readonly', 'max_threads', "
        "'max_execution_time', 'max_memory_usage') ORDER BY name FORMAT JSONEachRow"
    )
    reply = httpx.post(url, content=sql.encode(), auth=("analyst", "a-pw"))
    got = {row["name"]: row["value"] for row in map(json.loads, reply.text.splitlines())}
    assert got == {
        "readonly": "1",
        "max_threads": "1",
        "max_execution_time": "30",
        "max_memory_usage": str(2 * 1024**3),
    }
    again = httpx.post(url, content=b"SELECT 1 SETTINGS max_threads = 8", auth=("analyst", "a-pw"))
    assert again.status_code == 403 and "readonly" in again.text.lower()
