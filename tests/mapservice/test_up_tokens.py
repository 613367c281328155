"""What `mapservice up` prints about the API's tokens: where each generated one is and what
it opens (the values stay in the files)."""

from __future__ import annotations

from mapservice.local.up import api_token_rows
from mapservice.runtime.secrets import stored_secret
from mapservice.settings import Settings


def test_up_names_the_generated_token_files_not_their_values(tmp_path) -> None:
    """The table points at DATA_DIR/secrets/{writer,admin}-token (generated now) and says reads are open."""
    rows = dict(api_token_rows(Settings(data_dir=tmp_path)))
    writer, admin = stored_secret(tmp_path, "writer-token"), stored_secret(tmp_path, "admin-token")
    assert writer and admin
    assert str(tmp_path / "secrets" / "writer-token") in rows["API writer token (robots)"]
    assert str(tmp_path / "secrets" / "admin-token") in rows["API admin token"]
    assert all(writer not in v and admin not in v for v in rows.values())
    assert "API reader token" not in rows and rows["API reads"].startswith("open")


def test_up_names_configured_tokens_by_their_variable(tmp_path) -> None:
    """A token set in the environment is named by its variable; with reads by token, the reader row appears."""
    rows = dict(
        api_token_rows(
            Settings(data_dir=tmp_path, api_writer_tokens="w" * 32, api_read_access="token")
        )
    )
    assert rows["API writer token (robots)"].startswith("MAPSERVICE_API_WRITER_TOKENS")
    assert str(tmp_path / "secrets" / "reader-token") in rows["API reader token"]
    assert rows["API reads"] == "need a token"


def test_up_generates_and_names_an_operator_token(tmp_path) -> None:
    """Operators edit zones with a token of their own: `up` generates it (DATA_DIR/secrets/
    operator-token), names its file, and the API process reads the same one."""
    from mapservice.runtime.secrets import with_local_api_secrets
    from mapservice.settings import token_list

    rows = dict(api_token_rows(Settings(data_dir=tmp_path)))
    operator = stored_secret(tmp_path, "operator-token")
    assert operator and str(tmp_path / "secrets" / "operator-token") in rows["API operator token"]
    assert all(operator not in v for v in rows.values())
    served = with_local_api_secrets(Settings(data_dir=tmp_path))
    assert token_list(served.api_operator_tokens) == [operator]
