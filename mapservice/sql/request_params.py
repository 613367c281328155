"""The protocol parameters that name things (query_id, database, user, ...): printable text,
or a 400 that names the parameter and the character.

A `query_id` comes back in the X-ClickHouse-Query-Id header: a CR/LF in it would split the
response's head (the HTTP layer refuses to send it and drops the connection), a character
outside Latin-1 cannot be sent in a header at all. The others are not echoed, but they
reach the engine and the logs, where a control character has no business either. Checked
the same way wherever they arrive: URL parameters, form fields, X-ClickHouse-* headers.
"""

from __future__ import annotations

import unicodedata
from collections.abc import Mapping

from mapservice.sql.engine import SqlError

BAD_ARGUMENTS = 36
# Echoed in a response header, or a name ClickHouse itself keeps to ASCII: printable ASCII.
ASCII_PARAMS = frozenset({"query_id", "session_id", "default_format"})
# Names: printable text (any script), no control, format or line-separator characters.
TEXT_PARAMS = frozenset({"database", "user", "quota_key", "role"})
NAMING_PARAMS = ASCII_PARAMS | TEXT_PARAMS
# The headers that carry the same values (X-ClickHouse-Key, a password, is not a name).
NAMING_HEADERS = {
    "x-clickhouse-user": "user",
    "x-clickhouse-database": "database",
    "x-clickhouse-format": "default_format",
    "x-clickhouse-quota": "quota_key",
}


def _refusal(name: str, value: str, at: int, how: str) -> SqlError:
    char = value[at]
    label = unicodedata.name(char, f"U+{ord(char):04X}")
    return SqlError(
        f"The {name} parameter has {label} (U+{ord(char):04X}) at position {at}: {name} "
        f"must be {how}; send it without control or line-break characters",
        BAD_ARGUMENTS,
    )


def check_value(name: str, value: str) -> None:
    """Raises a 400 SqlError unless `value` is fit for the parameter `name`."""
    ascii_only = name in ASCII_PARAMS
    for at, char in enumerate(value):
        if ascii_only and not " " <= char <= "~":
            raise _refusal(name, value, at, "printable ASCII")
        if not char.isprintable():
            raise _refusal(name, value, at, "printable text")


def check_params(params: Mapping[str, str], headers: Mapping[str, str] | None = None) -> None:
    """Checks the naming parameters among `params` and the headers that carry them."""
    for name in NAMING_PARAMS:
        if name in params:
            check_value(name, params[name])
    for header, name in NAMING_HEADERS.items():
        if headers is not None and header in headers:
            check_value(name, headers[header])
