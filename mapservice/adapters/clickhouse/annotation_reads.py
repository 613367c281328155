"""Reads of the annotation edits (schema v13): the annotations standing at an instant and
the edits in a window: `ClickHouseAnnotationReads`, the AnnotationReader role, over the
store's connection, and `edit_of` (a stored row as its edit), which the retention uses too."""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

from mapservice.adapters.clickhouse.connection import ClickHouseConnection
from mapservice.core.annotations import (
    AnnotationChanged,
    AnnotationCreated,
    AnnotationEdit,
    AnnotationRemoved,
    CurrentAnnotation,
    ZoneViolation,
    fold_annotations,
    from_doc,
)

_COLUMNS = "toUnixTimestamp64Milli(ts), event_id, change, annotation_id, author, body"


def edit_of(row: Sequence[Any], check: bool = False) -> AnnotationEdit:
    """A stored row as the edit it records (not validated again unless `check`)."""
    ts, event_id, change, annotation_id, author, body = row
    if change == "removed":
        return AnnotationEdit(int(ts), event_id, AnnotationRemoved(annotation_id, author))
    kind = AnnotationCreated if change == "created" else AnnotationChanged
    return AnnotationEdit(
        int(ts), event_id, kind(annotation_id, author, from_doc(json.loads(body), check=check))
    )


class ClickHouseAnnotationReads:
    def __init__(self, connection: ClickHouseConnection) -> None:
        self.connection = connection

    def annotations_at(self, at_ms: int) -> list[CurrentAnnotation]:
        """The annotations standing at `at_ms` (inclusive), by id: each id's edits up to
        then folded (a few per annotation; the retention keeps them few)."""
        rows = self.connection.rows(
            f"SELECT {_COLUMNS} FROM {self.connection.database}.annotation_events FINAL "
            "WHERE ts <= fromUnixTimestamp64Milli({t:Int64}) ORDER BY annotation_id, ts, event_id",
            {"t": at_ms},
        )
        current = fold_annotations([edit_of(r) for r in rows], at_ms)
        return [current[k] for k in sorted(current)]

    def annotation_edits(
        self, from_ms: int, to_ms: int, limit: int = 10_000
    ) -> list[AnnotationEdit]:
        """The edits with from_ms <= time < to_ms, oldest first."""
        rows = self.connection.rows(
            f"SELECT {_COLUMNS} FROM {self.connection.database}.annotation_events FINAL "
            "WHERE ts >= fromUnixTimestamp64Milli({f:Int64}) AND ts < fromUnixTimestamp64Milli({t:Int64}) "
            "ORDER BY ts, event_id LIMIT {n:UInt32}",
            {"f": from_ms, "t": to_ms, "n": limit},
        )
        return [edit_of(r) for r in rows]

    def zone_violations(
        self, from_ms: int, to_ms: int, limit: int = 100_000
    ) -> list[ZoneViolation]:
        rows = self.connection.rows(
            f"SELECT toUnixTimestamp64Milli(ts), robot_id, annotation_id, x, y FROM "
            f"{self.connection.database}.zone_violations FINAL WHERE ts >= fromUnixTimestamp64Milli({{f:Int64}}) "
            "AND ts < fromUnixTimestamp64Milli({t:Int64}) ORDER BY ts, robot_id, annotation_id "
            "LIMIT {n:UInt32}",
            {"f": from_ms, "t": to_ms, "n": limit},
        )
        return [ZoneViolation(int(t), r, a, float(x), float(y)) for t, r, a, x, y in rows]
