"""The analyst credential: set (MAPSERVICE_ANALYST_PASSWORD), or in local mode generated
once and kept in the data dir, so `make up` needs no setup and no password is public."""

from __future__ import annotations

from pathlib import Path

from mapservice.runtime.secrets import local_secret, secrets_dir
from mapservice.settings import Settings
from mapservice.sql.http_protocol import SqlUser
from mapservice.sql.query_gate import QueryGate
from mapservice.sql.read_only import ReadOnlyLimits

ANALYST_PASSWORD_FILE = "analyst-password"


def analyst_password_file(data_dir: Path) -> Path:
    return secrets_dir(data_dir) / ANALYST_PASSWORD_FILE


def analyst_password(settings: Settings) -> str | None:
    """The analyst's password, or None where analyst SQL is off (production without one)."""
    configured = settings.analyst_password.get_secret_value()
    if configured:
        return configured
    if settings.mode != "local":
        return None
    return local_secret(settings.data_dir, ANALYST_PASSWORD_FILE, nbytes=18)


def analyst_user(settings: Settings) -> SqlUser | None:
    password = analyst_password(settings)
    return SqlUser(settings.analyst_username, password, read_only=True) if password else None


def analyst_limits(settings: Settings) -> ReadOnlyLimits:
    """Each statement's limits; its memory a share of the analysts' total, so that
    ANALYST_MAX_CONCURRENT_QUERIES statements together stay within it."""
    share = settings.analyst_max_memory_total_bytes // settings.analyst_max_concurrent_queries
    return ReadOnlyLimits(
        settings.analyst_max_execution_s,
        settings.analyst_max_result_rows,
        min(settings.analyst_max_memory_bytes, share),
        settings.analyst_max_threads,
    )


def analyst_gate(settings: Settings) -> QueryGate:
    """The analysts' own threads and queue (one per process serving them)."""
    return QueryGate(
        settings.analyst_max_concurrent_queries,
        settings.analyst_max_queued_queries,
        settings.analyst_queue_timeout_s,
    )
