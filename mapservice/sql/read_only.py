"""What an analyst's statement may be, checked by the engine's own parser.

The engine enforces read-only itself (`readonly = 1`: no writes, no DDL, no table functions
that reach files, URLs or programs, no change of a setting, so no lifting of the limits).
Two things it still allows are refused here, from ClickHouse's own parse of the statement
(`formatQuerySingleLine`, `EXPLAIN AST`), never from a regular expression over raw text:

- more than one statement (chDB runs `a; b`; a ClickHouse server over HTTP does not);
- a statement that is not a read (e.g. `KILL QUERY`), `INTO OUTFILE` (chDB writes the file
  on the service's disk) and the `python()` table function (reads this process's objects).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace

from mapservice.sql.engine import READONLY, SqlEngine, SqlError, SqlRequest

# Root nodes of EXPLAIN AST for statements that only read.
READ_STATEMENTS = frozenset({
    "SelectWithUnionQuery", "SelectIntersectExceptQuery", "ShowTables", "ShowDatabases",
    "ShowColumns", "DescribeQuery", "ExistsTableQuery", "ExistsDatabaseQuery",
    "ExistsViewQuery", "ShowCreateTableQuery", "ShowCreateViewQuery",
    "ShowCreateDatabaseQuery", "Explain",
})
FORBIDDEN_FUNCTIONS = frozenset({"python"})
_INTO_OUTFILE = re.compile(r"\bINTO\s+OUTFILE\b", re.IGNORECASE)


@dataclass(frozen=True)
class ReadOnlyLimits:
    """What one analyst statement may use; applied before the handle turns read-only."""

    max_execution_time_s: int = 30
    max_result_rows: int = 1_000_000
    max_memory_bytes: int = 2 * 1024**3

    def settings(self) -> dict[str, str]:
        return {
            "max_execution_time": str(self.max_execution_time_s),
            "max_result_rows": str(self.max_result_rows),
            "result_overflow_mode": "throw",
            "max_memory_usage": str(self.max_memory_bytes),
        }


def escape_parameter(value: str) -> str:
    """A query parameter's value as ClickHouse parses it (the escaped TSV form: a raw
    newline would end the value)."""
    return (value.replace("\\", "\\\\").replace("\n", "\\n").replace("\t", "\\t")
            .replace("\r", "\\r").replace("\0", "\\0"))


def statement_kind(ast_text: str) -> str:
    """The root node's name in `EXPLAIN AST` output (`SelectWithUnionQuery (children 1)`)."""
    first = ast_text.strip().splitlines()[0] if ast_text.strip() else ""
    return first.split(" ", 1)[0]


def functions_in(ast_text: str) -> set[str]:
    return {line.split()[1] for line in ast_text.splitlines()
            if line.strip().startswith("Function ") and len(line.split()) > 1}


def check_read_only(engine: SqlEngine, request: SqlRequest) -> str:
    """The statement as ClickHouse formats it (what then runs, so what was checked is what
    runs); raises SqlError (READONLY, or the parser's SYNTAX_ERROR) unless it is one read."""
    probe = replace(request, read_only=True, settings={}, default_format="TSVRaw")
    canonical = engine.execute(replace(
        probe, sql="SELECT formatQuerySingleLine({statement:String})",
        params={"statement": escape_parameter(request.sql)})).body.decode().strip()
    if _INTO_OUTFILE.search(canonical):
        raise SqlError("INTO OUTFILE is not allowed here: the result comes back in the reply",
                       READONLY)
    ast = engine.execute(replace(probe, sql=f"EXPLAIN AST {canonical}")).body.decode()
    kind = statement_kind(ast)
    if kind not in READ_STATEMENTS:
        raise SqlError(f"Only reads are allowed for this user; this statement is {kind}", READONLY)
    forbidden = functions_in(ast) & FORBIDDEN_FUNCTIONS
    if forbidden:
        raise SqlError(f"Function {sorted(forbidden)[0]} is not allowed for this user", READONLY)
    return canonical
