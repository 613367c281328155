"""The SQL engine port: one statement in, the engine's output bytes out.

Both adapters (chDB in this process, a ClickHouse server over HTTP) pass the same contract
suite (tests/mapservice/sql/test_engine_contract.py)."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Protocol

# ClickHouse error codes this package answers with itself.
SYNTAX_ERROR = 62
UNKNOWN_TABLE = 60
UNKNOWN_DATABASE = 81
READONLY = 164
AUTHENTICATION_FAILED = 516
UNKNOWN_SETTING = 115
NOT_IMPLEMENTED = 48
ACCESS_DENIED = 497
TIMEOUT_EXCEEDED = 159
TOO_MANY_SIMULTANEOUS_QUERIES = 202

_CODE = re.compile(r"Code: (\d+)\.")


@dataclass(frozen=True)
class SqlRequest:
    """One statement as the ClickHouse HTTP interface carries it."""

    sql: str
    database: str | None = None
    default_format: str = "TabSeparated"
    params: dict[str, str] = field(default_factory=dict)  # {name:Type} placeholders, by name
    settings: dict[str, str] = field(default_factory=dict)
    read_only: bool = False
    # An analyst's own statement (not the service's check of one): an engine with the
    # analysts' own credential on its server runs it as that user.
    analyst: bool = False


@dataclass(frozen=True)
class SqlResult:
    body: bytes
    format: str


class SqlError(Exception):
    """An error as ClickHouse reports it: a numeric code and a `Code: N. DB::Exception` text."""

    def __init__(self, message: str, code: int | None = None):
        if code is None:
            found = _CODE.search(message)
            code = int(found.group(1)) if found else 1000
        if not message.startswith("Code:"):
            message = f"Code: {code}. DB::Exception: {message}"
        super().__init__(message)
        self.code = code

    @property
    def http_status(self) -> int:
        """The status a ClickHouse server answers this error with over HTTP."""
        if self.code in (
            SYNTAX_ERROR,
            UNKNOWN_SETTING,
            NOT_IMPLEMENTED,
            27,
            36,
            47,
            53,
            130,
            131,
            271,
            457,
        ):
            return 400
        if self.code in (READONLY, AUTHENTICATION_FAILED, ACCESS_DENIED):
            return 403
        if self.code == TOO_MANY_SIMULTANEOUS_QUERIES:
            return 503
        if self.code in (UNKNOWN_TABLE, UNKNOWN_DATABASE):
            return 404
        if self.code == TIMEOUT_EXCEEDED:  # a statement stopped by max_execution_time
            return 408
        return 500


class SqlEngine(Protocol):
    def execute(self, request: SqlRequest) -> SqlResult:
        """Runs one statement; raises SqlError as ClickHouse would."""

    def insert(self, target: str, fmt: str, data: bytes, request: SqlRequest) -> SqlResult:
        """`INSERT INTO <target> FORMAT <fmt>` with `data` as its rows."""

    def ping(self) -> bool: ...

    def close(self) -> None: ...


_TRAILING_FORMAT = re.compile(r"\bFORMAT\s+(\w+)\s*;?\s*$", re.IGNORECASE)


def output_format(sql: str, default: str) -> str:
    """The format the output comes in: the statement's own FORMAT clause, else the default."""
    found = _TRAILING_FORMAT.search(sql)
    return found.group(1) if found else default
