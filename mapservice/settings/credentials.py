"""Credential settings' shared rules: the token lists and the values production refuses."""

from __future__ import annotations

import re

from pydantic import SecretStr

# The admin token the service had as its default until local mode generated one: a
# publicly known value, refused wherever it is still set in production.
DEFAULT_ADMIN_TOKEN = "local-admin-token"
DEFAULT_CLICKHOUSE_PASSWORD = ""
MIN_TOKEN_CHARS = 32  # `openssl rand -hex 32` gives 64; a 32-character hex token is 128 bits


def token_list(secret: SecretStr) -> list[str]:
    """The tokens of a comma- or whitespace-separated token setting (empty: none)."""
    return [t for t in re.split(r"[\s,]+", secret.get_secret_value()) if t]


def robot_tokens(secret: SecretStr) -> dict[str, str]:
    """`robotId=token` pairs of MAPSERVICE_API_ROBOT_TOKENS, token -> robotId."""
    pairs = {}
    for item in token_list(secret):
        robot_id, sep, token = item.partition("=")
        if not sep or not robot_id or not token:
            raise ValueError(
                "MAPSERVICE_API_ROBOT_TOKENS takes robotId=token pairs, "
                "comma-separated (e.g. agv-7=$(openssl rand -hex 32))"
            )
        pairs[token] = robot_id
    return pairs
