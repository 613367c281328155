"""Secrets that local mode makes itself: generated once, kept in DATA_DIR/secrets/ (mode
0600), and read back by every process of the same data dir, so `make up` needs no setup
and no credential of a running service is a value anyone can look up. Production never
generates: what it needs is set, and Settings refuses to start without it."""

from __future__ import annotations

import os
import secrets
import tempfile
from dataclasses import dataclass
from pathlib import Path

from pydantic import SecretStr

from mapservice.settings import Settings, token_list

# The files of DATA_DIR/secrets/, by what they hold.
ADMIN_TOKEN_FILE = "admin-token"
WRITER_TOKEN_FILE = "writer-token"
READER_TOKEN_FILE = "reader-token"
OPERATOR_TOKEN_FILE = "operator-token"
WEBHOOK_SIGNING_KEY_FILE = "webhook-signing-key"


def secrets_dir(data_dir: Path) -> Path:
    return Path(data_dir) / "secrets"


def local_secret(data_dir: Path, name: str, nbytes: int = 32) -> str:
    """The secret stored as DATA_DIR/secrets/<name>, generated on first use."""
    path = secrets_dir(data_dir) / name
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        os.chmod(path.parent, 0o700)
        # Written aside, then linked into place: two processes starting at once (`up` and
        # `serve`) end with the same secret, and nobody reads a half-written file.
        fd, tmp = tempfile.mkstemp(dir=path.parent)  # mode 0600
        with os.fdopen(fd, "w") as file:
            file.write(secrets.token_urlsafe(nbytes) + "\n")
        try:
            os.link(tmp, path)
        except FileExistsError:
            pass
        finally:
            os.unlink(tmp)
    return path.read_text().strip()


def stored_secret(data_dir: Path, name: str) -> str | None:
    """A secret local mode generated earlier, or None (never generates: for clients)."""
    path = secrets_dir(data_dir) / name
    try:
        return path.read_text().strip() or None
    except OSError:
        return None


@dataclass(frozen=True)
class ApiSecrets:
    """The API's credentials as a process runs with them (after local generation)."""

    admin: str
    writers: tuple[str, ...]
    readers: tuple[str, ...]


def with_local_api_secrets(settings: Settings) -> Settings:
    """In local mode, the settings with every unset API credential generated (or read back)
    from the data dir; in production, the settings as they are (they were validated)."""
    if settings.mode != "local":
        return settings
    update: dict[str, SecretStr] = {}
    if not settings.admin_token.get_secret_value():
        update["admin_token"] = SecretStr(local_secret(settings.data_dir, ADMIN_TOKEN_FILE))
    if not token_list(settings.api_writer_tokens):
        update["api_writer_tokens"] = SecretStr(local_secret(settings.data_dir, WRITER_TOKEN_FILE))
    if not token_list(settings.api_operator_tokens):
        update["api_operator_tokens"] = SecretStr(
            local_secret(settings.data_dir, OPERATOR_TOKEN_FILE)
        )
    if settings.api_read_access == "token" and not token_list(settings.api_reader_tokens):
        update["api_reader_tokens"] = SecretStr(local_secret(settings.data_dir, READER_TOKEN_FILE))
    return settings.model_copy(update=update) if update else settings


def with_local_webhook_key(settings: Settings) -> Settings:
    """In local mode, the settings with the webhooks' signing key generated (or read back)
    from the data dir when unset, so the API and the processors of one data dir derive the
    same secrets; in production, as they are (without a key, no webhooks)."""
    if settings.mode != "local" or settings.webhook_signing_key.get_secret_value():
        return settings
    key = SecretStr(local_secret(settings.data_dir, WEBHOOK_SIGNING_KEY_FILE))
    return settings.model_copy(update={"webhook_signing_key": key})


def api_secrets(settings: Settings) -> ApiSecrets:
    """The credentials of `settings` as plain lists (call with_local_api_secrets first)."""
    return ApiSecrets(
        admin=settings.admin_token.get_secret_value(),
        writers=tuple(token_list(settings.api_writer_tokens)),
        readers=tuple(token_list(settings.api_reader_tokens)),
    )
