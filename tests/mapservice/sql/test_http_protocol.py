"""The ClickHouse HTTP interface as clients meet it: clickhouse-connect and plain HTTP
against the chDB engine of this process."""

from __future__ import annotations

import datetime as dt
import gzip

import clickhouse_connect
import httpx
import lz4.frame
import pytest

from mapservice.sql.chdb_engine import ChdbEngine
from mapservice.sql.engine import SqlRequest
from mapservice.sql.http_protocol import MAX_QUERY_BYTES, SqlUser, clickhouse_http_app
from mapservice.sql.read_only import ReadOnlyLimits

from .serving import ServedApp

UTC = dt.UTC


@pytest.fixture(scope="module")
def url(tmp_path_factory):
    engine = ChdbEngine(
        tmp_path_factory.mktemp("http") / "ch",
        read_only_settings=ReadOnlyLimits(max_result_rows=5000).settings(),
    )
    engine.execute(SqlRequest("CREATE DATABASE IF NOT EXISTS h"))
    engine.execute(
        SqlRequest(
            "CREATE TABLE IF NOT EXISTS h.t (n UInt32, s String, "
            "at DateTime64(3, 'UTC')) ENGINE = MergeTree ORDER BY n"
        )
    )
    app = clickhouse_http_app(
        engine,
        [SqlUser("writer", "w-pw", read_only=False), SqlUser("analyst", "a-pw", read_only=True)],
        read_only_database="h",
    )
    with ServedApp(app) as served:
        yield served.url
    engine.close()


def client(url: str, user: str, password: str, **kw):
    host, port = url.removeprefix("http://").split(":")
    return clickhouse_connect.get_client(
        host=host, port=int(port), username=user, password=password, **kw
    )


@pytest.mark.parametrize("compress", ["lz4", "gzip", False])
def test_clickhouse_connect_inserts_and_reads_back(url, compress) -> None:
    """clickhouse-connect's inserts (each compression) and typed reads work unchanged."""
    writer = client(url, "writer", "w-pw", compress=compress, database="h")
    writer.command("TRUNCATE TABLE h.t")
    at = dt.datetime(2026, 11, 1, 12, 0, 0, 250_000, tzinfo=UTC)
    writer.insert("t", [[1, "one", at], [2, "two", at]], column_names=["n", "s", "at"])
    got = writer.query("SELECT n, s, at FROM t ORDER BY n").result_rows
    assert [(n, s) for n, s, _ in got] == [(1, "one"), (2, "two")]
    assert got[0][2].replace(tzinfo=UTC) == at
    assert writer.query(
        "SELECT n FROM t WHERE s = {s:String}", parameters={"s": "two"}
    ).result_rows == [(2,)]


def test_ping_answers_ok(url) -> None:
    """GET /ping is `Ok.` as on a server (load balancers and clients probe it)."""
    assert httpx.get(f"{url}/ping").text == "Ok.\n"


@pytest.mark.parametrize(
    "user,password", [("analyst", "wrong"), ("nobody", "a-pw"), ("default", "")]
)
def test_wrong_credentials_are_refused(url, user, password) -> None:
    """A wrong password or unknown user: 403 with code 516, nothing runs."""
    reply = httpx.post(url, content=b"SELECT 1", auth=(user, password))
    assert reply.status_code == 403
    assert reply.headers["X-ClickHouse-Exception-Code"] == "516"
    assert "Authentication failed" in reply.text


def test_the_analyst_reads_with_clickhouse_connect_but_cannot_write(url) -> None:
    """Read-only user: queries work; an insert through the same client is refused (164)."""
    analyst = client(url, "analyst", "a-pw")
    assert analyst.query("SELECT count() FROM h.t").result_rows[0][0] >= 0
    with pytest.raises(Exception, match="164"):
        analyst.insert(
            "h.t", [[9, "x", dt.datetime(2026, 1, 1, tzinfo=UTC)]], column_names=["n", "s", "at"]
        )
    with pytest.raises(Exception, match="164"):
        analyst.command("TRUNCATE TABLE h.t")


@pytest.mark.parametrize(
    "sql,why",
    [
        ("SELECT 1; DROP TABLE h.t", "Multi-statements"),
        ("SELECT 1 INTO OUTFILE '/tmp/mapservice-outfile'", "INTO OUTFILE"),
        ("KILL QUERY WHERE 1", "KillQueryQuery"),
        ("SELECT * FROM python(x)", "Table function python is not allowed"),
        (
            "SELECT * FROM file('/etc/hostname', 'LineAsString')",
            "Table function file is not allowed",
        ),
        ("SELECT * FROM url('http://127.0.0.1:9/x', 'CSV')", "Table function url is not allowed"),
        ("SELECT 1 SETTINGS max_result_rows = 100000000", "readonly"),
        ("SELECT number FROM system.numbers LIMIT 100000", "TOO_MANY_ROWS"),
    ],
)
def test_the_analyst_runs_only_one_bounded_read(url, sql, why) -> None:
    """Anything but one read within the limits is refused, with ClickHouse's reason."""
    reply = httpx.post(url, content=sql.encode(), auth=("analyst", "a-pw"))
    assert reply.status_code in (400, 403, 500) and why in reply.text, reply.text


def test_reads_come_in_any_clickhouse_format(url) -> None:
    """default_format or a FORMAT clause picks the output, named in X-ClickHouse-Format."""
    reply = httpx.post(
        url,
        params={"default_format": "CSVWithNames"},
        content=b"SELECT 1 AS one",
        auth=("analyst", "a-pw"),
    )
    assert reply.text == '"one"\n1\n' and reply.headers["X-ClickHouse-Format"] == "CSVWithNames"
    parquet = httpx.post(url, content=b"SELECT 1 AS one FORMAT Parquet", auth=("analyst", "a-pw"))
    assert parquet.content[:4] == b"PAR1"


def test_credentials_in_headers_or_parameters(url) -> None:
    """X-ClickHouse-User/Key headers and user/password parameters work like basic auth."""
    assert (
        httpx.get(url, params={"query": "SELECT 7", "user": "analyst", "password": "a-pw"}).text
        == "7\n"
    )
    assert (
        httpx.post(
            url,
            content=b"SELECT 8",
            headers={"X-ClickHouse-User": "analyst", "X-ClickHouse-Key": "a-pw"},
        ).text
        == "8\n"
    )


def test_a_statement_larger_than_the_limit_is_refused_unread(url) -> None:
    """A read-only request body over 1 MB: 400 without echoing it."""
    reply = httpx.post(
        url, content=b"SELECT '" + b"x" * (MAX_QUERY_BYTES + 10) + b"'", auth=("analyst", "a-pw")
    )
    assert reply.status_code == 400 and len(reply.content) < 300


def test_a_body_that_does_not_decode_is_a_clear_400(url) -> None:
    """Content-Encoding that lies: 400 naming the encoding, not a 500."""
    for encoding in ("gzip", "lz4", "brotli"):
        reply = httpx.post(
            url,
            content=b"not compressed",
            auth=("writer", "w-pw"),
            headers={"Content-Encoding": encoding},
        )
        assert 400 <= reply.status_code < 500 and encoding in reply.text


def test_set_lasts_one_request(url) -> None:
    """Without sessions a SET changes nothing for the next request (as on a server)."""
    auth = ("writer", "w-pw")
    assert httpx.post(url, content=b"SET max_threads = 3", auth=auth).status_code == 200
    assert httpx.post(url, content=b"SELECT getSetting('max_threads') = 3", auth=auth).text == "0\n"


def test_compressed_statements_in_the_body(url) -> None:
    """gzip and lz4 request bodies are decoded (clickhouse-connect compresses inserts)."""
    for body in (gzip.compress(b"SELECT 41 + 1"), lz4.frame.compress(b"SELECT 41 + 1")):
        encoding = "gzip" if body[:2] == b"\x1f\x8b" else "lz4"
        reply = httpx.post(
            url, content=body, auth=("analyst", "a-pw"), headers={"Content-Encoding": encoding}
        )
        assert reply.text == "42\n"


def test_bound_parameters_over_4_kb_come_as_multipart_and_work(url) -> None:
    """clickhouse-connect sends bound parameters over 4,096 bytes as multipart/form-data
    fields (the statement as `query`, each parameter as `param_<name>`), as a ClickHouse
    server accepts them: a 2,000-value IN list, for the writer and for the analyst."""
    from clickhouse_connect.driver.binding import MAX_URL_BIND_PARAM_LENGTH

    writer = client(url, "writer", "w-pw", database="h")
    writer.command("TRUNCATE TABLE h.t")
    hashes = [f"{n:032x}" for n in range(2000)]
    at = dt.datetime(2026, 11, 1, tzinfo=UTC)
    writer.insert(
        "t", [[n, hashes[n], at] for n in range(0, 2000, 7)], column_names=["n", "s", "at"]
    )
    assert len(",".join(hashes)) > MAX_URL_BIND_PARAM_LENGTH
    sql = "SELECT count(), sum(n) FROM h.t WHERE s IN {hashes:Array(String)}"
    expected = [(len(range(0, 2000, 7)), sum(range(0, 2000, 7)))]
    assert writer.query(sql, parameters={"hashes": hashes}).result_rows == expected
    analyst = client(url, "analyst", "a-pw")
    assert analyst.query(sql, parameters={"hashes": hashes}).result_rows == expected


def test_a_form_body_is_read_as_fields(url) -> None:
    """multipart/form-data bodies: `query` and `param_*` fields; a file part (external
    data) or a broken body is a clear 4xx. A urlencoded body is the statement (what curl
    --data-binary sends), as on a server."""
    auth = ("analyst", "a-pw")
    sql = "SELECT {a:UInt32} + {b:UInt32}"
    assert (
        httpx.post(
            url,
            files={"query": (None, sql), "param_a": (None, "40"), "param_b": (None, "2")},
            auth=auth,
        ).text
        == "42\n"
    )
    assert (
        httpx.post(
            url,
            content=b"SELECT 5",
            auth=auth,
            headers={"Content-Type": "application/x-www-form-urlencoded"},
        ).text
        == "5\n"
    )
    external = httpx.post(
        url, files={"query": (None, "SELECT 1"), "t": ("t.tsv", b"1\n")}, auth=auth
    )
    assert external.status_code == 400 and "External data" in external.text
    broken = httpx.post(
        url,
        content=b"--nope\r\n",
        auth=auth,
        headers={"Content-Type": "multipart/form-data; boundary=zzz"},
    )
    assert broken.status_code == 400 and "multipart" in broken.text
