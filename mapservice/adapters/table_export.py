"""Tabular exports: a time window of the analysts' views (and of the VDA 5050, annotation
and command event tables) as CSV or Parquet, written by ClickHouse itself.

May depend on: the store's ClickHouse client (`export_query`); dataset and view names come
from TABLES here, never from a request."""

from __future__ import annotations

# Dataset -> (view, its time column). Names come from here, never from a request.
TABLES: dict[str, tuple[str, str]] = {
    "robot-poses": ("robot_poses", "at"),
    "chunk-changes": ("chunk_changes", "at"),
    "chunk-conflicts": ("chunk_conflicts", "at"),
    "dead-letters": ("dead_letter_messages", "received_at"),
    # VDA 5050 vehicles' facts beyond their poses: their tables are already in analysts'
    # units (metres, radians, UTC times), read with FINAL (a redelivery is stored once).
    "vehicle-states": ("vda_states", "ts"),
    "vehicle-errors": ("vda_errors", "ts"),
    "vehicle-connections": ("vda_connections", "ts"),
    # Operators' annotation edits (who, when, the annotation as JSON) and their commands
    # with the robots' answers: event tables, read with FINAL like the VDA ones.
    "annotation-edits": ("annotation_events", "ts"),
    "commands": ("command_events", "ts"),
}
_READ_FINAL = {
    "vda_states",
    "vda_errors",
    "vda_connections",
    "annotation_events",
    "command_events",
}  # tables, not views
_NO_ROBOT = {"dead-letters", "annotation-edits"}  # datasets without a robot_id column
TABLE_FORMATS = {
    "csv": ("CSVWithNames", "text/csv"),
    "parquet": ("Parquet", "application/vnd.apache.parquet"),
}


def export_table(
    store, dataset: str, fmt: str, from_ms: int, to_ms: int, robot_id: str | None = None
) -> bytes:
    """`dataset` rows with from <= time < to, in ClickHouse's CSVWithNames or Parquet."""
    view, time_column = TABLES[dataset]
    clickhouse_format, _ = TABLE_FORMATS[fmt]
    robot_filter = " AND robot_id = {robot:String}" if robot_id and dataset not in _NO_ROBOT else ""
    final = " FINAL" if view in _READ_FINAL else ""
    sql = (
        f"SELECT * FROM {store.database}.{view}{final} WHERE {time_column} >= "
        "fromUnixTimestamp64Milli({from_ms:Int64}, 'UTC') AND "
        f"{time_column} < fromUnixTimestamp64Milli({{to_ms:Int64}}, 'UTC'){robot_filter} "
        f"ORDER BY {time_column}"
    )
    return store.export_query(
        sql, {"from_ms": from_ms, "to_ms": to_ms, "robot": robot_id or ""}, clickhouse_format
    )
