"""What an analyst's statement may call and read: an allow-list, checked on ClickHouse's
own parse of the statement (`EXPLAIN AST`), never on the raw text.

- **Functions**: the names in `allowed_functions.txt`, generated from the engine's
  `system.functions` by the rule below (`python -m mapservice.sql.allow_list > ...`) and
  committed, so an engine upgrade adds no function by itself (tests/mapservice/sql/
  test_allow_list.py says when the committed list is behind the engine's). Names are
  matched as the engine matches them: exactly, or in any case where the engine's function
  is case-insensitive; aliases count as their target; an aggregate function with
  combinators (`sumIf`, `uniqMergeState`, `groupArrayOrNull`) counts as its base.
- **Table functions**: only those that make rows out of nothing or out of a subquery
  (`numbers`, `values`, `view`, ...); every table function that reads files, URLs,
  object stores, other servers, programs or other tables by pattern is refused.
- **Tables**: every table and view of the service's database, and a few system tables
  that describe the schema and the functions (`ALLOWED_SYSTEM_TABLES`).

docs/analysts.md ("What SQL you may use") documents the rule for analysts.
"""

from __future__ import annotations

import re
import sys
from dataclasses import dataclass
from functools import cache
from pathlib import Path

# system.functions categories whose functions only compute on their arguments.
ALLOWED_CATEGORIES = frozenset(
    {
        "Aggregate Functions",
        "Arithmetic",
        "Arrays",
        "Bit",
        "Bitmap",
        "Comparison",
        "Conditional",
        "Dates and Times",
        "Distance",
        "Encoding",
        "Financial",
        "Geo",
        "Geo Polygon",
        "Hash",
        "IP Address",
        "JSON",
        "Logical",
        "Machine Learning",
        "Map",
        "Mathematical",
        "Null",
        "NumericIndexedVector",
        "QBit",
        "Random Number",
        "Rounding",
        "String",
        "String Replacement",
        "String Search",
        "String Splitting",
        "Time Series",
        "Time Window",
        "Tuple",
        "Type Conversion",
        "URL",
        "UUID",
    }
)
# Functions of the other categories ("Other", "Internal") that also only compute on their
# arguments or on the rows of the statement. Not here, and so refused: file() and
# filesystem*() (files), the ai*() functions (network), dictGet*/dictHas/region* (the
# service defines no dictionary; others are the server's), joinGet and hasColumnInTable
# (read tables by name, past the table check), getSetting/getServerSetting/getMacro/
# hostName/FQDN/currentUser/showCertificate/getClientHTTPHeader and the like (server
# internals), the introspection functions, encryption.
EXTRA_ALLOWED = frozenset(
    {
        "_CAST",
        "caseWithExpression",
        "MACNumToString",
        "MACStringToNum",
        "MACStringToOUI",
        "bar",
        "blockNumber",
        "blockSize",
        "byteSize",
        "colorOKLABToSRGB",
        "colorOKLCHToSRGB",
        "colorSRGBToOKLAB",
        "colorSRGBToOKLCH",
        "countDigits",
        "currentDatabase",
        "defaultValueOfArgumentType",
        "defaultValueOfTypeName",
        "digits",
        "finalizeAggregation",
        "flipCoordinates",
        "formatReadableDecimalSize",
        "formatReadableQuantity",
        "formatReadableSize",
        "formatReadableTimeDelta",
        "getSizeOfEnumType",
        "getSubcolumn",
        "identity",
        "ignore",
        "indexHint",
        "initializeAggregation",
        "isConstant",
        "isDecimalOverflow",
        "materialize",
        "minSampleSizeContinuous",
        "minSampleSizeConversion",
        "neighbor",
        "parseISO8601Duration",
        "parseReadableSize",
        "parseReadableSizeOrNull",
        "parseReadableSizeOrZero",
        "parseTimeDelta",
        "rowNumberInAllBlocks",
        "rowNumberInBlock",
        "runningAccumulate",
        "runningDifference",
        "runningDifferenceStartingWithFirstValue",
        # sleep holds one of the analysts' few query slots, nothing else (at most 3 s a block).
        "sleep",
        "sleepEachRow",
        "throwIf",
        "toColumnTypeName",
        "toTypeName",
        "transform",
        "variantElement",
        "variantType",
        "visibleWidth",
        # Clients ask on connecting (clickhouse-connect: SELECT version(), timezone()).
        "version",
    }
)
# Allowed-category functions that still reach beyond the arguments.
EXCLUDED = frozenset({"flameGraph", "serverTimezone"})
# Aggregate function combinators, longest first (system.aggregate_function_combinators).
COMBINATORS = (
    "SimpleState",
    "OrDefault",
    "Resample",
    "Distinct",
    "ForEach",
    "OrNull",
    "ArgMin",
    "ArgMax",
    "State",
    "Merge",
    "Array",
    "Tuple",
    "Null",
    "Map",
    "If",
)
ALLOWED_TABLE_FUNCTIONS = {
    name.lower(): name
    for name in (
        "numbers",
        "numbers_mt",
        "zeros",
        "zeros_mt",
        "values",
        "generateSeries",
        "generate_series",
        "view",
    )
}
ALLOWED_SYSTEM_TABLES = frozenset(
    {
        "one",
        "numbers",
        "numbers_mt",
        "zeros",
        "zeros_mt",
        "databases",
        "tables",
        "columns",
        "functions",
        "table_functions",
        "aggregate_function_combinators",
        "data_type_families",
        "time_zones",
        # Clients read it on connecting (clickhouse-connect: name, value, readonly); no secret
        # is a setting of this service.
        "settings",
    }
)
# Functions that call an aggregate function named by their first argument, a string
# (system.functions documents each as taking an aggregate function's name): that name
# is checked like a call.
BY_NAME_CALLERS = frozenset({"arrayReduce", "arrayReduceInRanges", "initializeAggregation"})
# Operators the parser writes as functions that system.functions does not list.
PARSER_FUNCTIONS = frozenset({"lambda"})
# AST nodes that call a function the dump does not name (`SELECT * APPLY(f)`).
OPAQUE_NODES = {"ColumnsApplyTransformer": "the APPLY column transformer"}
IN_FUNCTIONS = frozenset(
    {
        "in",
        "notIn",
        "globalIn",
        "globalNotIn",
        "nullIn",
        "notNullIn",
        "globalNullIn",
        "globalNotNullIn",
    }
)
_CATALOGUE = Path(__file__).with_name("allowed_functions.txt")
_REACHES_OUT = re.compile(
    r"file|url|s3|hdfs|remote|mysql|postgres|exec|python|azure|gcs|"
    r"redis|mongo|sqlite|odbc|jdbc|input|dict|^ai[A-Z]|iceberg|delta|"
    r"hudi|paimon|cluster|setting|macro|host|user|certificate|header",
    re.IGNORECASE,
)


class NotAllowed(ValueError):
    """A function, table function or table the analysts' allow-list does not hold."""


@dataclass(frozen=True)
class Catalogue:
    exact: frozenset[str]
    any_case: frozenset[str]  # lower-cased names of case-insensitive functions
    aggregates: frozenset[str]  # lower-cased: aggregate names (combinator bases)
    aggregates_exact: frozenset[str]

    def allows(self, name: str) -> bool:
        if name in PARSER_FUNCTIONS or name in self.exact or name.lower() in self.any_case:
            return True
        return self._aggregate_with_combinators(name)

    def _aggregate_with_combinators(self, name: str) -> bool:
        for suffix in COMBINATORS:
            if name.endswith(suffix) and len(name) > len(suffix):
                base = name[: -len(suffix)]
                if base in self.aggregates_exact or base.lower() in self.aggregates:
                    return True
                if self._aggregate_with_combinators(base):
                    return True
        return False


def catalogue_lines(rows: list[tuple[str, str, str, int, int]]) -> list[str]:
    """The allow-list file from system.functions rows (name, categories, alias_to,
    case_insensitive, is_aggregate): one `name<TAB>flags` line per allowed name, `i` for a
    case-insensitive name, `a` for an aggregate function."""
    by_name = {row[0]: row for row in rows}

    def allowed(name: str) -> bool:
        _, categories, alias_to, _, _ = by_name[name]
        if alias_to:
            return alias_to in by_name and alias_to != name and allowed(alias_to)
        if name in EXCLUDED:
            return False
        return name in EXTRA_ALLOWED or bool(
            {c.strip() for c in categories.split(",") if c.strip()} & ALLOWED_CATEGORIES
        )

    lines = []
    for name in sorted(by_name):
        if allowed(name):
            _, _, _, insensitive, aggregate = by_name[name]
            lines.append(f"{name}\t{'i' if insensitive else ''}{'a' if aggregate else ''}")
    return lines


@cache
def catalogue() -> Catalogue:
    exact, any_case, aggregates, aggregates_exact = set(), set(), set(), set()
    for line in _CATALOGUE.read_text().splitlines():
        if not line or line.startswith("#"):
            continue
        name, _, flags = line.partition("\t")
        exact.add(name)
        if "i" in flags:
            any_case.add(name.lower())
        if "a" in flags:
            aggregates_exact.add(name)
            if "i" in flags:
                aggregates.add(name.lower())
    return Catalogue(
        frozenset(exact), frozenset(any_case), frozenset(aggregates), frozenset(aggregates_exact)
    )


# --- the statement's parse -------------------------------------------------------------


@dataclass
class Node:
    kind: str
    words: list[str]  # what follows the kind on its line, `(alias x)`/`(children n)` removed
    children: list[Node]


_DECORATION = re.compile(r"\s*\((alias [^)]*|children \d+)\)")


def quoted_identifiers(canonical: str) -> list[str]:
    """The backquoted identifiers of a statement as formatQuerySingleLine writes it (string
    literals skipped), their escapes as written."""
    found, i = [], 0
    while i < len(canonical):
        quote = canonical[i]
        if quote in "'`":
            j = i + 1
            while j < len(canonical) and canonical[j] != quote:
                j += 2 if canonical[j] == "\\" else 1
            if quote == "`":
                found.append(canonical[i + 1 : j])
            i = j + 1
        else:
            i += 1
    return found


def check_identifiers(canonical: str) -> None:
    """EXPLAIN AST prints identifiers raw: one with a line break would start lines of the
    dump that are not nodes (and could move real nodes under them). Refused."""
    for name in quoted_identifiers(canonical):
        if "\\n" in name or "\\r" in name or "\n" in name or "\r" in name:
            raise NotAllowed(f"Identifier `{name}` has a line break; rename it without one")


def parse_ast(text: str) -> Node:
    """`EXPLAIN AST` output (one node a line, one space of indent a level) as a tree: its
    root, or a node holding every top-level node if there is more than one."""
    root = Node("", [], [])
    stack: list[tuple[int, Node]] = [(-1, root)]
    for line in text.split("\n"):
        if not line.strip():
            continue
        depth = len(line) - len(line.lstrip(" "))
        head = _DECORATION.sub("", line.strip())
        kind, *words = head.split(" ")
        node = Node(kind, words, [])
        while stack[-1][0] >= depth:
            stack.pop()
        stack[-1][1].children.append(node)
        stack.append((depth, node))
    return root.children[0] if len(root.children) == 1 else root


def _refuse_function(name: str) -> NotAllowed:
    why = (
        " (it reads files, the network, dictionaries or the server's own state)"
        if _REACHES_OUT.search(name)
        else ""
    )
    return NotAllowed(
        f"Function {name} is not allowed for analysts{why}: only functions "
        "that compute on the statement's own values are "
        "(the allow-list is in docs/analysts.md, 'What SQL you may use')"
    )


def _check_named_function(caller: str, node: Node) -> None:
    """`arrayReduce('sumIf', ...)`: the first argument, a string literal, names a function
    the allow-list holds (its parameters, `'quantile(0.9)'`, aside)."""
    arguments = node.children[0].children if node.children else []
    first = arguments[0] if arguments else None
    literal = " ".join(first.words) if first and first.kind == "Literal" else ""
    if not (len(literal) > 2 and literal[0] == literal[-1] == "'"):
        raise NotAllowed(
            f"{caller} takes the name of an aggregate function as a string literal here"
        )
    named = literal[1:-1].split("(", 1)[0].strip()
    if not catalogue().allows(named):
        raise _refuse_function(named)


def check_table(name: str, database: str) -> None:
    """`db.table` or `table` (in the analyst's database, where CTE names also live)."""
    db, dot, table = name.partition(".")
    if not dot or db == database:
        return
    if db == "system" and table in ALLOWED_SYSTEM_TABLES:
        return
    raise NotAllowed(
        f"Table {name} is not readable for analysts: only the tables and views of database "
        f"{database} and system.{{{', '.join(sorted(ALLOWED_SYSTEM_TABLES))}}} are"
    )


def check_database(name: str, database: str) -> None:
    if name not in (database, "system"):
        raise NotAllowed(
            f"Database {name} is not readable for analysts: only {database} "
            "(and the listed system tables) are"
        )


def check_tree(node: Node, database: str, parent: Node | None = None) -> None:
    """Raises NotAllowed for the first function, table function or table of the statement
    (subqueries, CTEs, lambdas, JOINs, IN and EXPLAIN included) outside the allow-list."""
    if node.kind in OPAQUE_NODES:
        raise NotAllowed(
            f"{OPAQUE_NODES[node.kind]} is not allowed for analysts: the function "
            "it applies cannot be checked; call the function on the columns"
        )
    if node.kind == "Function" and node.words:
        name = node.words[0]
        if parent is not None and parent.kind == "TableExpression":
            if name.lower() not in ALLOWED_TABLE_FUNCTIONS:
                raise NotAllowed(
                    f"Table function {name} is not allowed for analysts: only "
                    f"{', '.join(sorted(ALLOWED_TABLE_FUNCTIONS.values()))} are (no files, "
                    "URLs, object stores, other servers or programs)"
                )
        elif not catalogue().allows(name):
            raise _refuse_function(name)
        elif name in BY_NAME_CALLERS:
            _check_named_function(name, node)
        if name in IN_FUNCTIONS and node.children and len(node.children[0].children) == 2:
            right = node.children[0].children[1]
            if right.kind == "Identifier" and right.words:
                check_table(right.words[0], database)
    elif node.kind == "TableIdentifier" and node.words:
        check_table(node.words[0], database)
    elif (
        node.kind
        in (
            "ShowCreateTableQuery",
            "ShowCreateViewQuery",
            "ExistsTableQuery",
            "ExistsViewQuery",
            "ShowCreateDictionaryQuery",
        )
        and len(node.words) >= 2
    ):
        check_table(f"{node.words[0]}.{node.words[1]}", database)
        return
    elif node.kind in (
        "ShowTables",
        "ShowColumns",
        "ShowCreateDatabaseQuery",
        "ExistsDatabaseQuery",
    ):
        identifiers = [c.words[0] for c in node.children if c.kind == "Identifier" and c.words]
        if node.kind == "ShowColumns" and identifiers:
            check_table(
                ".".join(identifiers[-2:][::-1]) if len(identifiers) > 1 else identifiers[0],
                database,
            )
        elif identifiers:
            check_database(identifiers[0], database)
        elif node.words:
            check_database(node.words[0], database)
    for child in node.children:
        check_tree(child, database, node)


def main() -> None:
    """Prints the allow-list file for this chDB's system.functions."""
    import chdb

    out = (
        chdb.query(
            "SELECT name, categories, alias_to, case_insensitive, is_aggregate "
            "FROM system.functions WHERE origin = 'System'",
            "TSVRaw",
        )
        .bytes()
        .decode()
    )
    rows = []
    for line in out.splitlines():
        name, categories, alias_to, insensitive, aggregate = line.split("\t")
        rows.append((name, categories, alias_to, int(insensitive), int(aggregate)))
    version = str(chdb.query("SELECT version()", "TSVRaw")).strip()
    sys.stdout.write(
        f"# Functions analysts may call (mapservice/sql/allow_list.py), from "
        f"ClickHouse {version}'s system.functions.\n"
        "# Regenerate: python -m mapservice.sql.allow_list > "
        "mapservice/sql/allowed_functions.txt\n"
    )
    sys.stdout.write("\n".join(catalogue_lines(rows)) + "\n")


if __name__ == "__main__":
    main()
