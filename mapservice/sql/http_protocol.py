"""The ClickHouse HTTP interface in front of a `SqlEngine`.

The part of the protocol that clickhouse-connect, Grafana's ClickHouse data source and curl
use: `GET /ping`; `GET|POST /?query=...` (or the statement as the POST body); `database`,
`default_format`, `query_id`, `param_<name>` and settings as URL parameters; credentials as
`X-ClickHouse-User`/`X-ClickHouse-Key`, HTTP basic auth or `user`/`password` parameters;
the statement and `param_<name>` as fields of a multipart/form-data body,
as clickhouse-connect sends bound parameters over 4 KB;
`INSERT ... FORMAT <fmt>` with the rows as the body (gzip, deflate, lz4 or zstd encoded);
errors as `Code: N. DB::Exception: ...` with `X-ClickHouse-Exception-Code` and the status
a server would send. Not here: sessions (`session_id` is accepted and ignored, so `SET`
lasts one request, as on a server without a session), progress headers, compressed
replies (replies are identity-encoded; every client handles that), external data (files
in the multipart body), the native TCP protocol (clickhouse-client speaks only that).

Read-only users (the analysts) run on their own bounded pool (`QueryGate`), never on the
anyio threads the rest of the process shares. A body is capped as sent and as decoded
(BODY_CAPS: the user's), and decoded and parsed on threads of its own
(mapservice/sql/request_body.py); the parameters that name things are checked before use
(mapservice/sql/request_params.py).
"""

from __future__ import annotations

import base64
import json
import re
import secrets
import uuid
from collections.abc import Mapping
from dataclasses import dataclass, replace

import structlog
from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import PlainTextResponse, Response
from starlette.routing import Route

from mapservice.sql.engine import AUTHENTICATION_FAILED, SqlEngine, SqlError, SqlRequest
from mapservice.sql.query_gate import QueryGate, TooManyQueries
from mapservice.sql.read_only import check_read_only
from mapservice.sql.request_body import BodyCap, body_work
from mapservice.sql.request_params import check_params
from mapservice.sql.settings_policy import check_headers, check_settings

log = structlog.get_logger(__name__)

# URL parameters of the HTTP interface that are not settings of the statement.
PROTOCOL_PARAMS = frozenset(
    {
        "query",
        "database",
        "default_format",
        "query_id",
        "session_id",
        "session_timeout",
        "session_check",
        "user",
        "password",
        "quota_key",
        "compress",
        "decompress",
        "enable_http_compression",
        "http_zlib_compression_level",
        "wait_end_of_query",
        "buffer_size",
        "client_protocol_version",
        "send_progress_in_http_headers",
        "http_headers_progress_interval_ms",
        "add_http_cors_header",
        "role",
        "cancel_http_readonly_queries_on_client_close",
        "http_response_buffer_size",
    }
)
MAX_QUERY_BYTES = 1024 * 1024
MAX_INSERT_BYTES = 256 * 1024 * 1024
# A body's cap, received and decoded, by whether its user is read-only.
BODY_CAPS = {
    True: BodyCap(
        MAX_QUERY_BYTES,
        "a read-only statement is at most this long; send shorter statements (a long list "
        "as one Array parameter)",
    ),
    False: BodyCap(
        MAX_INSERT_BYTES, "send the rows in several inserts, each at most this long decoded"
    ),
}
_INSERT = re.compile(
    r"^\s*INSERT\s+INTO\s+(?P<target>.+?)\s+FORMAT\s+(?P<fmt>\w+)\s*$", re.IGNORECASE | re.DOTALL
)
# The statement at the head of the body, the rows after its line (clickhouse-connect's form).
_INSERT_HEAD = re.compile(
    rb"^\s*INSERT\s+INTO\s+(?P<target>[^\n]+?)\s+FORMAT\s+(?P<fmt>\w+)[ \t]*\r?\n", re.IGNORECASE
)


@dataclass(frozen=True)
class SqlUser:
    name: str
    password: str
    read_only: bool


def _credentials(request: Request) -> tuple[str, str]:
    header = request.headers.get("authorization", "")
    if header.lower().startswith("basic "):
        try:
            name, _, password = base64.b64decode(header[6:]).decode().partition(":")
            return name, password
        except ValueError:
            return "", ""
    name = request.headers.get("x-clickhouse-user") or request.query_params.get("user") or "default"
    password = request.headers.get("x-clickhouse-key") or request.query_params.get("password") or ""
    return name, password


def _error(exc: SqlError, query_id: str) -> Response:
    headers = {"X-ClickHouse-Exception-Code": str(exc.code), "X-ClickHouse-Query-Id": query_id}
    if isinstance(exc, TooManyQueries):
        headers["Retry-After"] = str(exc.retry_after_s)
    return PlainTextResponse(str(exc) + "\n", status_code=exc.http_status, headers=headers)


def clickhouse_http_app(
    engine: SqlEngine,
    users: list[SqlUser],
    *,
    timezone: str = "UTC",
    display_name: str = "mapservice",
    read_only_database: str = "default",
    read_only_gate: QueryGate | None = None,
    read_only_limits: Mapping[str, str] | None = None,
) -> Starlette:
    """An ASGI app speaking the ClickHouse HTTP interface for `users`. Read-only ones get
    `check_read_only` (the allow-list; tables of `read_only_database`, also their default
    database), the settings policy (settings_policy.py; limits: `read_only_limits`, by
    default the engine's), the engine's read-only handles and `read_only_gate`'s threads."""
    by_name = {u.name: u for u in users}
    limits = dict(
        getattr(engine, "read_only_settings", {}) if read_only_limits is None else read_only_limits
    )
    gate = read_only_gate or QueryGate(concurrent=2, queued=8, queue_timeout_s=5)
    bodies = {True: body_work("read-only"), False: body_work("read-write")}

    def checked_and_run(sql_request: SqlRequest):
        checked = check_read_only(engine, sql_request, read_only_database, limits)
        return engine.execute(_with_sql(sql_request, checked))

    def authenticate(request: Request) -> SqlUser:
        name, password = _credentials(request)
        user = by_name.get(name)
        if user is None or not secrets.compare_digest(password.encode(), user.password.encode()):
            raise SqlError(
                f"{name}: Authentication failed: password is incorrect, or there "
                "is no user with such name",
                AUTHENTICATION_FAILED,
            )
        return user

    def identify(request: Request) -> str | None:
        """The caller's name for rate limits ("sql:<user>"), None without valid credentials
        (the API's AccessGuard then counts the client's address)."""
        try:
            return f"sql:{authenticate(request).name}"
        except SqlError:
            return None

    async def ping(request: Request) -> Response:
        return PlainTextResponse("Ok.\n")

    async def query(request: Request) -> Response:
        query_id = str(uuid.uuid4())  # until the caller's is known to be fit for a header
        headers = {
            "X-ClickHouse-Query-Id": query_id,
            "X-ClickHouse-Timezone": timezone,
            "X-ClickHouse-Server-Display-Name": display_name,
        }
        try:
            check_params(request.query_params, request.headers)
            query_id = request.query_params.get("query_id") or query_id
            headers["X-ClickHouse-Query-Id"] = query_id
            user = authenticate(request)
            url_query = request.query_params.get("query", "")
            if user.read_only:
                # Before the body is read: a refused setting costs nothing more.
                check_headers(request.headers.keys())
                check_settings(_settings_in(request.query_params), limits, "URL parameter")
            received = await bodies[user.read_only].read(request, BODY_CAPS[user.read_only])
            body, form = received.data, received.form
            params = dict(request.query_params)
            if user.read_only:
                check_settings(_settings_in(form or {}), limits, "form field")
            if form is not None:
                check_params(form)
                # The statement and its parameters in the body; the URL's still count.
                url_query = form.pop("query", "") or url_query
                params.update(form)
                body = b""
            database = params.get("database") or request.headers.get("x-clickhouse-database")
            if user.read_only:
                database = database or read_only_database
            sql_request = SqlRequest(
                sql="",
                database=database,
                default_format=params.get("default_format")
                or request.headers.get("x-clickhouse-format")
                or "TabSeparated",
                params={k[6:]: v for k, v in params.items() if k.startswith("param_")},
                settings=_settings_in(params),
                read_only=user.read_only,
                analyst=user.read_only,
            )
            insert = _INSERT.match(url_query) if body else None
            rows = body
            if not url_query and not user.read_only:
                insert = _INSERT_HEAD.match(body[:65536])
                rows = body[insert.end() :] if insert else body
            if insert and not user.read_only:
                target = insert["target"]
                target = target.decode() if isinstance(target, bytes) else target
                fmt = insert["fmt"].decode() if isinstance(insert["fmt"], bytes) else insert["fmt"]
                result = await run_in_threadpool(engine.insert, target, fmt, rows, sql_request)
            else:
                sql = (
                    url_query
                    + ("\n" if url_query and body else "")
                    + body.decode("utf-8", "replace")
                )
                if not sql.strip():
                    raise SqlError("Empty query: send it as ?query= or as the POST body", 62)
                sql_request = _with_sql(sql_request, sql)
                if user.read_only:
                    result = await gate.run(checked_and_run, sql_request)
                else:
                    result = await run_in_threadpool(engine.execute, sql_request)
        except SqlError as exc:
            log.info("sql refused", code=exc.code, error=str(exc)[:300], query_id=query_id)
            return _error(exc, query_id)
        headers["X-ClickHouse-Format"] = result.format
        headers["X-ClickHouse-Summary"] = json.dumps({"read_rows": "0", "written_rows": "0"})
        return Response(
            result.body,
            headers=headers,
            media_type="text/plain; charset=UTF-8"
            if "JSON" not in result.format
            else "application/json; charset=UTF-8",
        )

    app = Starlette(
        routes=[
            Route("/ping", ping, methods=["GET", "HEAD"]),
            Route("/", query, methods=["GET", "POST"]),
        ]
    )
    app.state.identify = identify
    return app


def _settings_in(fields: Mapping[str, str]) -> dict[str, str]:
    """The settings among a request's URL parameters or form fields: all but the
    protocol's own parameters and the bound `param_<name>` values."""
    return {
        k: v for k, v in fields.items() if k not in PROTOCOL_PARAMS and not k.startswith("param_")
    }


def _with_sql(request: SqlRequest, sql: str) -> SqlRequest:
    return replace(request, sql=sql)
