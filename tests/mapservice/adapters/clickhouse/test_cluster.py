"""The schema on a replicated cluster: each migration statement rewritten ON CLUSTER with
Replicated engines parses with ClickHouse's own parser (chDB) and keeps its meaning.
What this does not cover: running it on a real cluster (none can be installed here)."""

from __future__ import annotations

import re

import pytest

from mapservice.adapters.clickhouse.cluster import for_cluster
from mapservice.adapters.clickhouse.schema import migrations
from mapservice.sql.chdb_engine import ChdbEngine
from mapservice.sql.engine import SqlRequest
from mapservice.sql.read_only import escape_parameter

STATEMENTS = [s for m in migrations("mapservice", 7) for s in m.statements]


@pytest.fixture(scope="module")
def parse(tmp_path_factory):
    engine = ChdbEngine(tmp_path_factory.mktemp("cluster") / "ch")

    def formatted(statement: str) -> str:
        return (
            engine.execute(
                SqlRequest(
                    "SELECT formatQuerySingleLine({s:String})",
                    default_format="TSVRaw",
                    params={"s": escape_parameter(statement)},
                )
            )
            .body.decode()
            .strip()
        )

    yield formatted
    engine.close()


def test_without_a_cluster_nothing_changes() -> None:
    """An empty cluster name leaves every statement as it is."""
    assert [for_cluster(s, "") for s in STATEMENTS] == STATEMENTS


@pytest.mark.parametrize("statement", STATEMENTS, ids=lambda s: " ".join(s.split())[:60])
def test_every_ddl_statement_runs_on_the_cluster(parse, statement) -> None:
    """DDL gets ON CLUSTER (as ClickHouse parses it); MergeTree engines become Replicated; DML is untouched."""
    rewritten = parse(for_cluster(statement, "mapservice"))
    original = parse(statement)
    if re.match(r"(CREATE|ALTER|DROP|RENAME|TRUNCATE)\b", original):
        assert "ON CLUSTER mapservice" in rewritten
        assert _unreplicated(rewritten) == original  # nothing else changed
    else:
        assert rewritten == original
    for engine in re.findall(r"ENGINE = (\w+)", rewritten):
        assert engine.startswith("Replicated"), rewritten


def _unreplicated(text: str) -> str:
    return (
        re.sub(r"Replicated(\w*MergeTree)\('[^']*', '[^']*'(?:, )?", r"\1(", text)
        .replace(" ON CLUSTER mapservice", "")
        .replace("MergeTree()", "MergeTree")
    )


def test_replicated_engines_keep_their_version_column(parse) -> None:
    """ReplacingMergeTree(ts_a) becomes ReplicatedReplacingMergeTree(path, replica, ts_a)."""
    (conflicts,) = [
        s for s in STATEMENTS if "CREATE TABLE IF NOT EXISTS mapservice.conflicts_v5" in s
    ]
    rewritten = parse(for_cluster(conflicts, "c1"))
    assert (
        "ReplicatedReplacingMergeTree('/clickhouse/tables/{shard}/{database}/{table}', '{replica}', ts_a)"
        in rewritten
    )
