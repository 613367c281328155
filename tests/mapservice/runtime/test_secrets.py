"""Local mode's generated secrets (mapservice/runtime/secrets.py): made once per data dir,
private, read back by every process; never generated in production."""

from __future__ import annotations

import stat
import threading

import pytest
from pydantic import ValidationError

from mapservice.runtime.secrets import (
    ADMIN_TOKEN_FILE,
    READER_TOKEN_FILE,
    WEBHOOK_SIGNING_KEY_FILE,
    WRITER_TOKEN_FILE,
    api_secrets,
    local_secret,
    secrets_dir,
    stored_secret,
    with_local_api_secrets,
    with_local_webhook_key,
)
from mapservice.settings import MIN_TOKEN_CHARS, Settings
from mapservice.sql.credentials import analyst_password


def test_local_mode_generates_admin_and_writer_tokens_once(tmp_path) -> None:
    """The first start writes an admin and a writer token (0600, in a 0700 dir, long enough for production); the next reads the same ones."""
    first = api_secrets(with_local_api_secrets(Settings(data_dir=tmp_path)))
    again = api_secrets(with_local_api_secrets(Settings(data_dir=tmp_path)))
    assert first == again
    assert len(first.admin) >= MIN_TOKEN_CHARS and len(first.writers[0]) >= MIN_TOKEN_CHARS
    assert first.admin != first.writers[0] and first.readers == ()
    for name in (ADMIN_TOKEN_FILE, WRITER_TOKEN_FILE):
        mode = stat.S_IMODE((secrets_dir(tmp_path) / name).stat().st_mode)
        assert mode == 0o600, oct(mode)
    assert stat.S_IMODE(secrets_dir(tmp_path).stat().st_mode) == 0o700
    assert not (secrets_dir(tmp_path) / READER_TOKEN_FILE).exists()  # reads are open


def test_local_mode_generates_the_webhook_signing_key_once_and_production_never(tmp_path) -> None:
    """Every process of a data dir derives the same webhook secrets: the key is generated
    once (0600) and read back; a key that is set wins; production generates none."""
    first = with_local_webhook_key(Settings(data_dir=tmp_path)).webhook_signing_key
    again = with_local_webhook_key(Settings(data_dir=tmp_path)).webhook_signing_key
    assert first.get_secret_value() == again.get_secret_value()
    assert len(first.get_secret_value()) >= MIN_TOKEN_CHARS
    mode = stat.S_IMODE((secrets_dir(tmp_path) / WEBHOOK_SIGNING_KEY_FILE).stat().st_mode)
    assert mode == 0o600, oct(mode)
    set_ = Settings(data_dir=tmp_path, webhook_signing_key="k" * 32)
    assert with_local_webhook_key(set_) is set_
    elsewhere = tmp_path / "production"
    prod = Settings(data_dir=elsewhere, mode="production", admin_token="a" * 32)
    assert with_local_webhook_key(prod) is prod
    assert not secrets_dir(elsewhere).exists()


def test_production_refuses_a_short_webhook_signing_key() -> None:
    with pytest.raises(ValidationError, match="MAPSERVICE_WEBHOOK_SIGNING_KEY has 31"):
        Settings(mode="production", admin_token="a" * 32, webhook_signing_key="k" * 31)
    Settings(mode="production", admin_token="a" * 32, webhook_signing_key="k" * 32)


def test_reader_token_only_where_reads_need_one(tmp_path) -> None:
    """With MAPSERVICE_API_READ_ACCESS=token a reader token is generated too."""
    secrets = api_secrets(
        with_local_api_secrets(Settings(data_dir=tmp_path, api_read_access="token"))
    )
    assert secrets.readers == (stored_secret(tmp_path, READER_TOKEN_FILE),)


def test_configured_tokens_win_and_production_never_generates(tmp_path) -> None:
    """A token that is set is used as it is; production mode writes nothing to the data dir."""
    set_ = Settings(
        data_dir=tmp_path,
        admin_token="a" * 32,
        api_writer_tokens="w" * 32,
        api_operator_tokens="o" * 32,
    )
    assert api_secrets(with_local_api_secrets(set_)).admin == "a" * 32
    assert not secrets_dir(tmp_path).exists()
    prod = Settings(data_dir=tmp_path, mode="production", admin_token="a" * 32)
    assert with_local_api_secrets(prod) is prod
    assert api_secrets(prod).writers == ()
    assert not secrets_dir(tmp_path).exists()


def test_processes_starting_together_end_with_one_secret(tmp_path) -> None:
    """Eight threads generating at once all read the same secret (written aside, then linked)."""
    results: list[str] = []
    threads = [
        threading.Thread(target=lambda: results.append(local_secret(tmp_path, "x")))
        for _ in range(8)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(set(results)) == 1 and results[0]
    assert sorted(p.name for p in secrets_dir(tmp_path).iterdir()) == ["x"]


def test_stored_secret_never_generates(tmp_path) -> None:
    """Clients read a generated secret if there is one, and create none."""
    assert stored_secret(tmp_path, WRITER_TOKEN_FILE) is None
    assert not secrets_dir(tmp_path).exists()


def test_the_analyst_password_uses_the_same_files(tmp_path) -> None:
    """The analyst password is one more secret of the same kind (DATA_DIR/secrets/analyst-password)."""
    password = analyst_password(Settings(data_dir=tmp_path))
    assert password == stored_secret(tmp_path, "analyst-password")
