"""What an analyst's statement may be, checked by the engine's own parser.

The engine enforces read-only itself (`readonly = 1`: no writes, no DDL, no table functions
that reach files, URLs or programs, no change of a setting, so no lifting of the limits).
Two things it still allows are refused here, from ClickHouse's own parse of the statement
(`formatQuerySingleLine`, `EXPLAIN AST`), never from a regular expression over raw text:

- more than one statement (chDB runs `a; b`; a ClickHouse server over HTTP does not);
- a statement that is not a read (e.g. `KILL QUERY`) and `INTO OUTFILE` (chDB writes the
  file on the service's disk);
- under `readonly = 1` chDB (clickhouse-local) still runs the scalar `file()` (any path the
  process can read), `python()` and the other functions and table functions that reach
  outside the statement: every function, table function and table must be on the
  analysts' allow-list (mapservice/sql/allow_list.py).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, replace

from mapservice.sql.allow_list import Node, NotAllowed, check_identifiers, check_tree, parse_ast
from mapservice.sql.engine import ACCESS_DENIED, READONLY, SqlEngine, SqlError, SqlRequest
from mapservice.sql.settings_policy import check_setting, parameter_value, statement_settings

# Root nodes of EXPLAIN AST for statements that only read.
READ_STATEMENTS = frozenset(
    {
        "SelectWithUnionQuery",
        "SelectIntersectExceptQuery",
        "ShowTables",
        "ShowDatabases",
        "DescribeQuery",
        "ExistsTableQuery",
        "ExistsDatabaseQuery",
        "ExistsViewQuery",
        "ShowCreateTableQuery",
        "ShowCreateViewQuery",
        "ShowCreateDatabaseQuery",
        "Explain",
    }
)
_INTO_OUTFILE = re.compile(r"\bINTO\s+OUTFILE\b", re.IGNORECASE)
# EXPLAIN AST names SHOW TABLES, SHOW MERGES, SHOW CLUSTERS, SHOW FILESYSTEM CACHES alike
# (ShowTables); the formatted statement tells them apart. These read allowed tables only.
_SHOW_LISTS = re.compile(r"^SHOW (FULL )?(TEMPORARY )?(TABLES|DATABASES|DICTIONARIES|SETTINGS)\b")


@dataclass(frozen=True)
class ReadOnlyLimits:
    """What one analyst statement may use; applied before the handle turns read-only."""

    max_execution_time_s: int = 30
    max_result_rows: int = 1_000_000
    max_memory_bytes: int = 2 * 1024**3
    max_threads: int = 1

    def settings(self) -> dict[str, str]:
        return {
            "max_execution_time": str(self.max_execution_time_s),
            "max_result_rows": str(self.max_result_rows),
            "result_overflow_mode": "throw",
            "max_memory_usage": str(self.max_memory_bytes),
            "max_threads": str(self.max_threads),
        }


def escape_parameter(value: str) -> str:
    """A query parameter's value as ClickHouse parses it (the escaped TSV form: a raw
    newline would end the value)."""
    return (
        value.replace("\\", "\\\\")
        .replace("\n", "\\n")
        .replace("\t", "\\t")
        .replace("\r", "\\r")
        .replace("\0", "\\0")
    )


def statement_kind(ast_text: str) -> str:
    """The root node's name in `EXPLAIN AST` output (`SelectWithUnionQuery (children 1)`)."""
    first = ast_text.strip().splitlines()[0] if ast_text.strip() else ""
    return first.split(" ", 1)[0]


def check_read_only(
    engine: SqlEngine,
    request: SqlRequest,
    database: str,
    limits: Mapping[str, str] | None = None,
) -> str:
    """The statement as ClickHouse formats it (what then runs, so what was checked is what
    runs); raises SqlError (READONLY, ACCESS_DENIED, or the parser's SYNTAX_ERROR) unless it
    is one read of the allow-list's functions and of `database`'s tables whose SETTINGS
    clauses (or SET) change only what the settings policy allows under `limits`. `request`
    must carry `database` (unqualified names resolve there, as do the statement's CTE
    names)."""
    if request.database != database:
        raise SqlError(
            f"Database {request.database} is not readable for analysts: only {database} is",
            ACCESS_DENIED,
        )
    probe = replace(request, read_only=True, analyst=False, settings={}, default_format="TSVRaw")
    canonical = (
        engine.execute(
            replace(
                probe,
                sql="SELECT formatQuerySingleLine({statement:String})",
                params={"statement": escape_parameter(request.sql)},
            )
        )
        .body.decode()
        .strip()
    )
    if _INTO_OUTFILE.search(canonical):
        raise SqlError(
            "INTO OUTFILE is not allowed here: the result comes back in the reply", READONLY
        )
    # The engine first: under readonly = 1 EXPLAIN AST already refuses a SETTINGS clause
    # that changes a value; the settings policy then sees every clause.
    ast = engine.execute(replace(probe, sql=f"EXPLAIN AST {canonical}")).body.decode()
    kind = statement_kind(ast)
    tree = parse_ast(ast)
    clauses = statement_settings(canonical)
    for clause in clauses:
        for name, value in clause:
            check_setting(
                name, parameter_value(value, request.params), limits or {}, "in the statement"
            )
    _check_settings_clauses(clauses, tree)
    if kind == "Set":
        return canonical  # only allowed settings, and without a session it changes nothing
    if kind not in READ_STATEMENTS:
        hint = " (DESCRIBE TABLE shows a table's columns)" if kind == "ShowColumns" else ""
        raise SqlError(
            f"Only reads are allowed for this user; this statement is {kind}{hint}", READONLY
        )
    if kind == "ShowTables" and not _SHOW_LISTS.match(canonical):
        raise SqlError(
            f"{canonical.split(' FROM ')[0][:40]} is not allowed for analysts: "
            "SHOW TABLES, DATABASES, DICTIONARIES and SETTINGS are",
            ACCESS_DENIED,
        )
    try:
        check_identifiers(canonical)
        check_tree(tree, database)
    except NotAllowed as exc:
        raise SqlError(str(exc), ACCESS_DENIED) from exc
    return canonical


def _set_nodes(node: Node) -> int:
    """SETTINGS clauses and SET in the parse; an EXPLAIN's options (its first child) are
    a `Set` node too, and no settings."""
    children = node.children
    if node.kind == "Explain" and children and children[0].kind == "Set":
        children = children[1:]
    return (node.kind == "Set") + sum(_set_nodes(child) for child in children)


def _check_settings_clauses(clauses: list[list[tuple[str, str]]], tree: Node) -> None:
    """The engine's parse says how many SETTINGS clauses and SETs there are (`Set`
    nodes): a statement whose formatted text shows another number was not wholly checked
    by the settings policy, and is refused."""
    expected = _set_nodes(tree)
    if len(clauses) != expected:
        raise SqlError(
            f"The settings of this statement cannot be checked ({expected} SETTINGS clauses "
            f"in the parse, {len(clauses)} in the text); send settings as URL parameters",
            ACCESS_DENIED,
        )
