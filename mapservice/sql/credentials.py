"""The analyst credential: set (MAPSERVICE_ANALYST_PASSWORD), or in local mode generated
once and kept in the data dir, so `make up` needs no setup and no password is public."""

from __future__ import annotations

import os
import secrets
import tempfile
from pathlib import Path

from mapservice.settings import Settings

from mapservice.sql.http_protocol import SqlUser
from mapservice.sql.read_only import ReadOnlyLimits


def analyst_password_file(data_dir: Path) -> Path:
    return data_dir / "secrets" / "analyst-password"


def analyst_password(settings: Settings) -> str | None:
    """The analyst's password, or None where analyst SQL is off (production without one)."""
    configured = settings.analyst_password.get_secret_value()
    if configured:
        return configured
    if settings.mode != "local":
        return None
    path = analyst_password_file(settings.data_dir)
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        # Written aside, then linked into place: two processes starting at once (`up` and
        # `serve`) end with the same password, and nobody reads a half-written file.
        fd, tmp = tempfile.mkstemp(dir=path.parent)  # mode 0600
        with os.fdopen(fd, "w") as file:
            file.write(secrets.token_urlsafe(18) + "\n")
        try:
            os.link(tmp, path)
        except FileExistsError:
            pass
        finally:
            os.unlink(tmp)
    return path.read_text().strip()


def analyst_user(settings: Settings) -> SqlUser | None:
    password = analyst_password(settings)
    return SqlUser(settings.analyst_username, password, read_only=True) if password else None


def analyst_limits(settings: Settings) -> ReadOnlyLimits:
    return ReadOnlyLimits(settings.analyst_max_execution_s, settings.analyst_max_result_rows,
                          settings.analyst_max_memory_bytes)
