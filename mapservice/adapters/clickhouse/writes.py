"""The store's appends: events (poses, chunk writes and their contents, map metadata),
dead letters and conflicts, each batch through the writer client under its lock.

`ClickHouseHistoryWriter` (the HistoryWriter role) holds the connection and the store's
`snapshots.ClickHouseSnapshots`: a late event notes a snapshot repair. It depends on
nothing else of the store but the rows of `command_reads.command_row`.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import chain

import numpy as np

from mapservice.adapters.clickhouse import command_schema, incident_schema
from mapservice.adapters.clickhouse.command_reads import command_row
from mapservice.adapters.clickhouse.connection import (
    ClickHouseConnection,
    flag,
    json_encoder,
    mm,
)
from mapservice.adapters.clickhouse.incident_reads import incident_row
from mapservice.adapters.clickhouse.pose_schema import POSE_COLUMNS
from mapservice.adapters.clickhouse.snapshots import ClickHouseSnapshots
from mapservice.core.annotations import ANNOTATION_EVENTS, AnnotationRemoved, ZoneViolation, to_doc
from mapservice.core.commands import COMMAND_EVENTS
from mapservice.core.events import (
    ChunkUpdated,
    DeadLetter,
    Envelope,
    MapMetaSet,
    VdaConnectionReported,
    VdaFactsheetReported,
    VdaStateReported,
    pose_of,
)
from mapservice.core.incidents import Incident
from mapservice.core.ports import ConflictRow

POSE_INSERT_COLUMNS = [
    "robot_id",
    "ts",
    "x_mm",
    "y_mm",
    "z_mm",
    "qx",
    "qy",
    "qz",
    "qw",
    "battery",
    "charging",
    "loaded",
    "has_path",
    "path_x_mm",
    "path_y_mm",
    "recv_lag_ms",
]


class ClickHouseHistoryWriter:
    """append (append_events, then derive_views), append_dead_letters, append_conflicts."""

    def __init__(self, connection: ClickHouseConnection, snapshots: ClickHouseSnapshots) -> None:
        self.connection = connection
        self.snapshots = snapshots  # the one the snapshot timer builds with (the newest known)

    def append(self, events: Sequence[Envelope]) -> None:
        self.append_events(events)
        self.derive_views(events)

    def derive_views(self, events: Sequence[Envelope]) -> None:
        """Feeds the batch's poses to the pose views (schema v10: through the Null table
        `pose_derivations`); repeating it for a batch changes nothing.

        The poses are stored already, so ClickHouse reads them back itself over the spans
        of the batch's event times (`reread_spans`) instead of being sent every row
        again; poses of other batches in those spans are derived again, which changes
        nothing. A batch whose spans would re-read much more than itself (a backlog, late
        poses spread over minutes) sends its rows, as does a cluster: the re-read could
        run on a replica the batch's part has not reached yet."""
        pose_events = [e for e in events if pose_of(e.payload) is not None]
        if not pose_events:
            return
        spans = (
            None
            if self.connection.cluster
            else reread_spans([e.event_time_ms for e in pose_events])
        )
        with self.connection.lock:
            if spans is None:
                self.connection.insert(
                    "pose_derivations",
                    _pose_columns(pose_events),
                    POSE_INSERT_COLUMNS,
                    column_oriented=True,
                )
            else:
                self._derive_spans(spans)

    def _derive_spans(self, spans: Sequence[tuple[int, int]]) -> None:
        db = self.connection.database
        # Whole milliseconds from the stored events: written into the statement as integers.
        within = " OR ".join(
            f"(ts >= fromUnixTimestamp64Milli({int(lo)}) AND ts <= fromUnixTimestamp64Milli({int(hi)}))"
            for lo, hi in spans
        )
        # The re-read meets a part a full disk broke.
        with self.connection.reloading_broken_tables():
            self.connection.client.command(
                f"INSERT INTO {db}.pose_derivations ({POSE_COLUMNS}) "
                f"SELECT {POSE_COLUMNS} FROM {db}.poses WHERE {within}"
            )

    def derive_views_between(self, from_ms: int, to_ms: int) -> None:
        """derive_views for every pose stored with from_ms <= event time <= to_ms, read
        back inside ClickHouse: a bulk writer (the demo history) spares re-sending a batch
        it just stored (about as long as storing it). A pose derived twice changes nothing,
        so windows may overlap."""
        with self.connection.lock:
            self._derive_spans([(from_ms, to_ms)])

    def append_events(self, events: Sequence[Envelope]) -> None:
        pose_events, chunks, contents, metas, annotations, commands = [], [], [], [], [], []
        vda: dict[str, list] = {
            "vda_states": [],
            "vda_errors": [],
            "vda_connections": [],
            "vda_factsheets": [],
        }
        for e in events:
            p = e.payload
            if pose_of(p) is not None:
                pose_events.append(e)
            if isinstance(p, (VdaStateReported, VdaConnectionReported, VdaFactsheetReported)):
                _vda_rows(e, vda)
            elif isinstance(p, ChunkUpdated):
                chunks.append(
                    [
                        e.event_time_ms,
                        p.row,
                        p.column,
                        e.robot_id,
                        p.content_hash,
                        e.receive_time_ms - e.event_time_ms,
                    ]
                )
                day = e.event_time_ms // 86_400_000
                if self.connection.known_contents.get(p.content_hash) != day:
                    contents.append((p.content_hash, day, p.width, p.height, p.data))
            elif isinstance(p, MapMetaSet):
                metas.append(
                    [e.event_time_ms, e.robot_id, json_encoder.encode(p.to_2019()).decode()]
                )
            elif isinstance(p, ANNOTATION_EVENTS):
                annotations.append(_annotation_row(e))
            elif isinstance(p, COMMAND_EVENTS):
                commands.append(command_row(e))
        poses = _pose_columns(pose_events) if pose_events else None
        with self.connection.lock:
            if contents:
                # Contents first: an event must never reference pixels that are not stored.
                self.connection.insert(
                    "chunk_contents",
                    [list(x) for x in contents],
                    ["content_hash", "day", "width", "height", "zlib_pixels"],
                )
                for h, day, *_ in contents:
                    self.connection.known_contents[h] = day
                if len(self.connection.known_contents) > 1_000_000:
                    self.connection.known_contents.clear()
            if chunks:
                self.connection.insert(
                    "chunk_events",
                    chunks,
                    ["ts", "row", "col", "robot_id", "content_hash", "recv_lag_ms"],
                )
            if poses:
                self.connection.insert("poses", poses, POSE_INSERT_COLUMNS, column_oriented=True)
            if metas:
                self.connection.insert("map_meta", metas, ["ts", "robot_id", "meta"])
            for table, rows in vda.items():
                if rows:
                    self.connection.insert(table, rows, _VDA_COLUMNS[table])
            if annotations:
                self.connection.insert(
                    "annotation_events",
                    annotations,
                    [
                        "annotation_id",
                        "ts",
                        "event_id",
                        "change",
                        "author",
                        "shape",
                        "kind",
                        "name",
                        "body",
                    ],
                )
            if commands:
                self.connection.insert("command_events", commands, list(command_schema.COLUMNS))
            # A late event (at or before the newest snapshot) makes the snapshots from its
            # time on wrong. Noting that is all the batch waits for: reads stop using those
            # snapshots at once (they fold events from the last good one: exact, slower),
            # and the snapshot timer rebuilds them in bounded steps (repair_snapshots).
            times = [row[0] for row in chunks] + [e.event_time_ms for e in pose_events]
            if times:
                last = self.snapshots.newest_snapshot()
                if last is not None and min(times) <= last:
                    self.snapshots.note_repair(min(times))

    def append_dead_letters(self, records: Sequence[DeadLetter]) -> None:
        if not records:
            return
        rows = [
            [r.receive_time_ms, r.reason, r.mqtt_topic, r.detail, r.payload, r.gateway]
            for r in records
        ]
        with self.connection.lock:
            self.connection.insert(
                "dead_letters",
                rows,
                ["received", "reason", "mqtt_topic", "detail", "payload", "gateway"],
            )

    def append_zone_violations(self, rows: Sequence[ZoneViolation]) -> None:
        if rows:
            with self.connection.lock:
                self.connection.insert(
                    "zone_violations",
                    [[v.ts_ms, v.robot_id, v.annotation_id, v.x, v.y] for v in rows],
                    ["ts", "robot_id", "annotation_id", "x", "y"],
                )

    def append_incidents(
        self, found: Sequence[Incident], found_ms: int, retracted: Sequence[Incident] = ()
    ) -> None:
        rows = [
            incident_row(incident, found_ms, gone)
            for incidents, gone in ((found, False), (retracted, True))
            for incident in incidents
        ]
        if rows:
            with self.connection.lock:
                self.connection.insert(incident_schema.TABLE, rows, list(incident_schema.COLUMNS))

    def append_conflicts(self, rows: Sequence[ConflictRow]) -> None:
        if not rows:
            return
        data = [[c.ts_ms, c.row, c.column, c.robot_b, c.robot_a, c.ts_a_ms] for c in rows]
        with self.connection.lock:
            self.connection.insert(
                "conflicts", data, ["ts", "row", "col", "robot_b", "robot_a", "ts_a"]
            )


_VDA_COLUMNS = {
    "vda_states": [
        "robot_id",
        "ts",
        "manufacturer",
        "serial_number",
        "vda_version",
        "map_id",
        "on_known_map",
        "x",
        "y",
        "theta",
        "driving",
        "paused",
        "operating_mode",
        "order_id",
        "error_count",
    ],
    "vda_errors": ["robot_id", "ts", "level", "type", "description"],
    "vda_connections": ["robot_id", "ts", "state", "sent_ts"],
    "vda_factsheets": ["robot_id", "ts", "vda_version", "factsheet"],
}


def _annotation_row(e: Envelope) -> list:
    """An annotation edit as its `annotation_events` row (schema v13)."""
    p = e.payload
    change = e.type.removeprefix("annotation.")
    if isinstance(p, AnnotationRemoved):
        return [p.annotation_id, e.event_time_ms, e.event_id, change, p.author, "", "", "", ""]
    doc = to_doc(p.annotation)
    return [
        p.annotation_id,
        e.event_time_ms,
        e.event_id,
        change,
        p.author,
        doc["shape"],
        doc["kind"],
        doc["name"],
        json_encoder.encode(doc).decode(),
    ]


def _vda_rows(e: Envelope, out: dict[str, list]) -> None:
    """A VDA 5050 event's rows, by table (schema v12)."""
    p, at = e.payload, e.event_time_ms
    if isinstance(p, VdaStateReported):
        out["vda_states"].append(
            [
                e.robot_id,
                at,
                p.manufacturer,
                p.serial_number,
                p.vda_version,
                p.map_id,
                p.on_known_map,
                p.x,
                p.y,
                p.theta,
                p.driving,
                p.paused,
                p.operating_mode,
                p.order_id,
                len(p.errors),
            ]
        )
        out["vda_errors"].extend(
            [e.robot_id, at, err.level, err.type, err.description] for err in p.errors
        )
    elif isinstance(p, VdaConnectionReported):
        out["vda_connections"].append([e.robot_id, at, p.state, p.sent_time_ms])
    elif isinstance(p, VdaFactsheetReported):
        out["vda_factsheets"].append([e.robot_id, at, p.vda_version, p.factsheet_json])


# Event times at most this far apart are re-read as one span (a live batch is one span).
REREAD_GAP_MS = 1_000
# A batch is re-read only while its spans cover at most this much history in all (a live
# batch covers its window, about a second); beyond it re-reading costs more than the rows.
REREAD_MAX_MS = 5_000
REREAD_MAX_SPANS = 16


def reread_spans(times_ms: Sequence[int]) -> list[tuple[int, int]] | None:
    """The spans [first, last] of event times that `derive_views` re-reads for a batch
    with these event times, or None when re-reading them would cost more than sending
    the batch's rows (more than REREAD_MAX_MS of history or REREAD_MAX_SPANS spans)."""
    spans: list[tuple[int, int]] = []
    for t in sorted(times_ms):
        if spans and t - spans[-1][1] <= REREAD_GAP_MS:
            spans[-1] = (spans[-1][0], t)
        else:
            spans.append((t, t))
    if not spans or len(spans) > REREAD_MAX_SPANS:
        return None
    if sum(hi - lo for lo, hi in spans) > REREAD_MAX_MS:
        return None
    return spans


def _pose_columns(events: Sequence[Envelope]) -> list[list]:
    """Pose events (or VDA states' poses) as the columns `poses` (and `pose_derivations`)
    store, in POSE_INSERT_COLUMNS order: built column by column (the client would turn
    rows into columns again), and the positions and paths converted to millimetres for
    the whole batch at once (`_millimetres`). A batch of the demo history holds 100,000
    poses of up to a thousand path points each: per value in Python, that conversion
    was most of its insert."""
    poses = [pose_of(e.payload) for e in events]
    paths = [p.path or () for p in poses]
    positions = _millimetres([[p.position for p in poses]], 3)
    path_mm = _millimetres(paths, 2)
    path_x, path_y, at = [], [], 0
    for path in paths:
        end = at + len(path)
        path_x.append(path_mm[0][at:end])
        path_y.append(path_mm[1][at:end])
        at = end
    return [
        [e.robot_id for e in events],
        [e.event_time_ms for e in events],
        *positions,
        *(list(q) for q in zip(*(p.orientation for p in poses))),
        [p.battery_level for p in poses],
        [flag(p.charging) for p in poses],
        [flag(p.loaded) for p in poses],
        [p.path is not None for p in poses],
        path_x,
        path_y,
        [e.receive_time_ms - e.event_time_ms for e in events],
    ]


def _millimetres(groups: Sequence[Sequence[Sequence[float]]], width: int) -> list[list[int]]:
    """`mm` of every value of the groups' points of `width` coordinates each: one list per
    coordinate, the groups' points one after the other. numpy's rint of the same product
    rounds half to even as `round` does, so the integers are the same; values numpy cannot
    hold exactly (not finite, or beyond 2**52 mm) take `mm` one by one and fail as it
    fails."""
    points = list(chain.from_iterable(groups))
    if not points:
        return [[] for _ in range(width)]
    scaled = np.fromiter(chain.from_iterable(points), np.float64) * 1000
    if len(scaled) != width * len(points) or not (
        np.isfinite(scaled).all() and np.abs(scaled).max() < 2.0**52
    ):
        return [[mm(point[i]) for point in points] for i in range(width)]
    millimetres = np.rint(scaled).astype(np.int64)
    return [millimetres[i::width].tolist() for i in range(width)]
