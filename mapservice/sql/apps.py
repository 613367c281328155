"""The ClickHouse HTTP interface as each process offers it.

- the API's `/clickhouse` (every mode): the analyst only, read-only, on the service's own
  ClickHouse (chDB in this process, or the server the service writes to);
- `mapservice clickhouse-server` (embedded data dir, split deployment on one machine): the
  process that owns the chDB directory, for the service's ClickHouse user (read-write with
  `--read-write`) and the analyst.
"""

from __future__ import annotations

import ssl

import structlog
from starlette.applications import Starlette

from mapservice.settings import Settings
from mapservice.sql.credentials import analyst_gate, analyst_limits, analyst_user
from mapservice.sql.engine import SqlEngine, SqlRequest
from mapservice.sql.http_protocol import SqlUser, clickhouse_http_app
from mapservice.sql.server_engine import ServerEngine

log = structlog.get_logger(__name__)


def engine_for(settings: Settings, analyst_auth: tuple[str, str] | None = None) -> SqlEngine:
    """The engine over the service's ClickHouse; `analyst_auth`: the server credential for
    analysts' own statements (ServerEngine)."""
    dsn = settings.resolved_clickhouse_dsn
    limits = analyst_limits(settings).settings()
    if dsn.startswith("chdb://"):
        from mapservice.sql.chdb_engine import ChdbEngine

        return ChdbEngine(dsn, read_only_settings=limits)
    return ServerEngine(
        dsn,
        settings.clickhouse_username,
        settings.clickhouse_password.get_secret_value(),
        read_only_settings=limits,
        verify=clickhouse_verify(settings),
        analyst_auth=analyst_auth,
    )


def analyst_server_credential(settings: Settings, analyst: SqlUser) -> tuple[str, str] | None:
    """The credential `analyst`'s statements reach a ClickHouse server with: the configured
    analysts' user, or in local mode the analyst's own (`mapservice clickhouse-server`
    serves the analyst read-only); None: the service's user, read-only per request."""
    if settings.clickhouse_analyst_username:
        return (
            settings.clickhouse_analyst_username,
            settings.clickhouse_analyst_password.get_secret_value(),
        )
    if settings.mode == "local":
        return (analyst.name, analyst.password)
    if not settings.resolved_clickhouse_dsn.startswith("chdb://"):
        log.warning(
            "analysts' statements reach ClickHouse as the service's user (readonly=1 and "
            "the limits per request); set MAPSERVICE_CLICKHOUSE_ANALYST_USERNAME to a "
            "read-only user whose profile holds them"
        )
    return None


def clickhouse_verify(settings: Settings) -> bool | ssl.SSLContext:
    """httpx's `verify` for the ClickHouse server: the configured CA and client certificate
    (MAPSERVICE_CLICKHOUSE_*_FILE), or the system's CAs."""
    tls = settings.clickhouse_tls()
    if not tls:
        return True
    context = ssl.create_default_context(cafile=tls.get("ca_cert"))
    if "client_cert" in tls:
        context.load_cert_chain(tls["client_cert"], tls["client_cert_key"])
    return context


def engine_timezone(engine: SqlEngine) -> str:
    return (
        engine.execute(SqlRequest("SELECT timezone()", default_format="TSVRaw"))
        .body.decode()
        .strip()
        or "UTC"
    )


def analyst_app(settings: Settings) -> Starlette | None:
    """The analyst's read-only endpoint, or None where no analyst credential is configured."""
    user = analyst_user(settings)
    if user is None:
        return None
    engine = engine_for(settings, analyst_server_credential(settings, user))
    return clickhouse_http_app(
        engine,
        [user],
        timezone=engine_timezone(engine),
        display_name="mapservice-api",
        read_only_database=settings.clickhouse_database,
        read_only_gate=analyst_gate(settings),
    )


def server_app(settings: Settings, read_write: bool) -> Starlette:
    """The standalone server over the data dir's chDB (MAPSERVICE_CLICKHOUSE_DSN, if it is
    a chdb:// one; the processes it serves set theirs to this server's http:// address)."""
    from mapservice.sql.chdb_engine import ChdbEngine

    dsn = (
        settings.clickhouse_dsn
        if settings.clickhouse_dsn.startswith("chdb://")
        else f"chdb://{(settings.data_dir / 'clickhouse').resolve()}"
    )
    engine = ChdbEngine(dsn, read_only_settings=analyst_limits(settings).settings())
    users = []
    analyst = analyst_user(settings)
    if analyst is not None:
        users.append(analyst)
    users.append(
        SqlUser(
            settings.clickhouse_username,
            settings.clickhouse_password.get_secret_value(),
            read_only=not read_write,
        )
    )
    app = clickhouse_http_app(
        engine,
        users,
        timezone=engine_timezone(engine),
        display_name="mapservice-clickhouse-server",
        read_only_database=settings.clickhouse_database,
        read_only_gate=analyst_gate(settings),
    )
    app.state.chdb_path = engine.path
    return app
