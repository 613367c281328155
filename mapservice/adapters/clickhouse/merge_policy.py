"""How the store's tables merge their parts: one policy for every MergeTree table of the
schema, set after each migration (so a table a later migration adds gets it too), on chDB
and a ClickHouse server alike.

Every insert writes a part into each table it reaches (the poses, and through the views
their tracks, key frames and aggregates), and ClickHouse merges them in the background.
Its merge selector weighs each part of a candidate range at its size plus a fixed 5 MiB,
allows a merge once that weight reaches `merge_selector_base` times the range's largest
part, and prefers the widest range. While a day's partition is a few MiB on disk (the
first hours of each day at tens of robots) the fixed cost makes every part look alike, so
with the default base (5) it merges the WHOLE partition with every few new parts: the
work per insert grows with the partition, and so does the CPU of the process that holds
the engine. A base of 20 makes a merge wait for about 20 parts of like
weight: the new parts merge among themselves, the day's big part is left alone until
about 20 parts its size stand beside it, and the rows merged per insert fall several
times. `min_parts_to_merge_at_once` (tried) is worse: once a partition holds one big part
and fewer than N small ones, the only range wide enough is the whole partition, which is
then rewritten every N inserts all day long.

What the base costs: a partition keeps more active parts (ten to twenty, not a handful),
which a read with FINAL merges as it reads (the newest seconds' window reads about a
quarter slower, older windows the same: BENCHMARKS.md). The count stays bounded, far from
the engine's limits: the selector lowers its base linearly towards 1 (merge any two
parts) as a partition's active parts go from 10 to 50, and as a range's youngest part
ages from 10 s to an hour, so a partition levels off under 50 parts while the merges keep
pace, well under `parts_to_delay_insert` (1000) and `parts_to_throw_insert` (3000).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import structlog

log = structlog.get_logger(__name__)

MERGE_POLICY: Mapping[str, int] = {"merge_selector_base": 20}


def _has_setting(engine_full: str, name: str, value: int) -> bool:
    """Whether a table's `engine_full` sets `name` to `value` already."""
    return re.search(rf"\b{re.escape(name)} = {value}(?:,|$)", engine_full) is not None


def set_on_every_merge_tree_table(
    database: str,
    settings: Mapping[str, int],
    command: Callable[[str], object],
    query_rows: Callable[[str], Iterable[tuple[Any, ...]]],
) -> list[str]:
    """Sets `settings` (ALTER TABLE ... MODIFY SETTING) on each MergeTree table of
    `database` that does not have them at these values; returns the tables changed. A
    setting the engine does not know (an older server) is left out rather than failing
    the migration."""
    known = {
        name
        for (name,) in query_rows(
            "SELECT name FROM system.merge_tree_settings WHERE name IN ("
            + ", ".join(f"'{name}'" for name in settings)
            + ")"
        )
    }
    wanted = {name: value for name, value in settings.items() if name in known}
    changed = []
    for table, engine_full in query_rows(
        f"SELECT name, engine_full FROM system.tables WHERE database = '{database}' "
        "AND engine LIKE '%MergeTree' AND NOT is_temporary ORDER BY name"
    ):
        missing = {n: v for n, v in wanted.items() if not _has_setting(engine_full, n, v)}
        if missing:
            assignments = ", ".join(f"{n} = {v}" for n, v in missing.items())
            command(f"ALTER TABLE {database}.{table} MODIFY SETTING {assignments}")
            changed.append(table)
    return changed


def apply_merge_policy(
    database: str,
    command: Callable[[str], object],
    query_rows: Callable[[str], Iterable[tuple[Any, ...]]],
) -> list[str]:
    """Gives every MergeTree table of `database` the MERGE_POLICY; returns the tables
    changed (none once applied)."""
    tables = set_on_every_merge_tree_table(database, MERGE_POLICY, command, query_rows)
    if tables:
        log.info(
            "merge policy set: new parts merge among themselves before the day's",
            settings=dict(MERGE_POLICY),
            tables=tables,
        )
    return tables
