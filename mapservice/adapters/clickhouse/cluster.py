"""The schema on a replicated ClickHouse cluster (MAPSERVICE_CLICKHOUSE_CLUSTER): every DDL
statement `ON CLUSTER`, every MergeTree table Replicated.

A pure rewrite of the migrations' statements, so one set of migrations serves a single
server, chDB and a cluster. The replica path uses the macros every replica defines (the
Altinity operator sets `{shard}` and `{replica}`), one path per database and table.
Tested offline: each rewritten statement parses with ClickHouse's own parser (chDB)."""

from __future__ import annotations

import re

REPLICA_PATH = "'/clickhouse/tables/{shard}/{database}/{table}', '{replica}'"

_NAME = r"[A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z_][A-Za-z0-9_]*)?"
# Statements whose target name is followed by the ON CLUSTER clause.
_AFTER_NAME = re.compile(
    rf"^(\s*(?:CREATE\s+(?:OR\s+REPLACE\s+)?(?:MATERIALIZED\s+)?(?:TABLE|VIEW|DATABASE)"
    rf"(?:\s+IF\s+NOT\s+EXISTS)?|ALTER\s+TABLE|DROP\s+(?:TABLE|VIEW)(?:\s+IF\s+EXISTS)?"
    rf"|TRUNCATE\s+TABLE(?:\s+IF\s+EXISTS)?)\s+{_NAME})",
    re.IGNORECASE,
)
_RENAME = re.compile(r"^\s*RENAME\s+TABLE\s", re.IGNORECASE)
_ENGINE = re.compile(
    r"ENGINE\s*=\s*(ReplacingMergeTree|AggregatingMergeTree|MergeTree)\b(\(([^)]*)\))?"
)


def replicated_engine(match: re.Match[str]) -> str:
    args = (match.group(3) or "").strip()
    return f"ENGINE = Replicated{match.group(1)}({REPLICA_PATH}{', ' + args if args else ''})"


def for_cluster(statement: str, cluster: str) -> str:
    """`statement` for the cluster `cluster`; unchanged when `cluster` is empty."""
    if not cluster:
        return statement
    on = f" ON CLUSTER '{cluster}'"
    if _RENAME.match(statement):
        return statement.rstrip() + on
    found = _AFTER_NAME.match(statement)
    if found is None:
        return statement  # INSERT, SELECT, OPTIMIZE...: not DDL, replication carries them
    if re.search(r"\bON\s+CLUSTER\b", statement, re.IGNORECASE):
        return statement
    rewritten = statement[: found.end()] + on + statement[found.end() :]
    return _ENGINE.sub(replicated_engine, rewritten)
