"""Exports people open elsewhere: a time window of the history as CSV or Parquet (written
by ClickHouse itself from the analysts' views) and as MCAP (Foxglove and Lichtblick replay
it: the map as a `foxglove.Grid`, each robot as `foxglove.PoseInFrame`).

May depend on: the ports and the analyst schema; the store's ClickHouse client for tables."""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import BinaryIO

import numpy as np

from mapservice.core.events import MapMetaSet
from mapservice.core.ports import HistoryStore, PoseRow

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
}
_READ_FINAL = {"vda_states", "vda_errors", "vda_connections"}  # tables, not views
TABLE_FORMATS = {"csv": ("CSVWithNames", "text/csv"),
                 "parquet": ("Parquet", "application/vnd.apache.parquet")}
MAP_TOPIC = "/map"
MAP_FRAME = "map"


def pose_topic(robot_id: str) -> str:
    return f"/robots/{robot_id}/pose"


def export_table(store, dataset: str, fmt: str, from_ms: int, to_ms: int,
                 robot_id: str | None = None) -> bytes:
    """`dataset` rows with from <= time < to, in ClickHouse's CSVWithNames or Parquet."""
    view, time_column = TABLES[dataset]
    clickhouse_format, _ = TABLE_FORMATS[fmt]
    robot_filter = " AND robot_id = {robot:String}" if robot_id and dataset != "dead-letters" else ""
    final = " FINAL" if view in _READ_FINAL else ""
    sql = (f"SELECT * FROM {store.database}.{view}{final} WHERE {time_column} >= "
           "fromUnixTimestamp64Milli({from_ms:Int64}, 'UTC') AND "
           f"{time_column} < fromUnixTimestamp64Milli({{to_ms:Int64}}, 'UTC'){robot_filter} "
           f"ORDER BY {time_column}")
    return store.export_query(sql, {"from_ms": from_ms, "to_ms": to_ms, "robot": robot_id or ""},
                              clickhouse_format)


@dataclass
class McapCounts:
    grids: int = 0
    poses: int = 0
    chunk_changes: int = 0


class _Floor:
    """The whole map as one image, updated chunk by chunk."""

    def __init__(self, meta: MapMetaSet, store: HistoryStore):
        self.meta, self.store = meta, store
        self.pixels = np.full((meta.height, meta.width), 205, dtype=np.uint8)  # ROS "unknown"
        self._contents: dict[str, tuple[int, int, bytes]] = {}

    def apply(self, changes: list[tuple[int, int, str]]) -> None:
        missing = [bytes.fromhex(h) for _, _, h in changes if h not in self._contents]
        if missing:
            for digest, content in self.store.chunk_contents(missing).items():
                self._contents[digest.hex()] = content
        cw, ch = self.meta.chunk_width, self.meta.chunk_height
        for row, col, digest in changes:
            content = self._contents.get(digest)
            if content is None:
                continue  # contents older than the retention: the chunk stays as it was
            width, height, data = content
            tile = np.frombuffer(zlib.decompress(data), dtype=np.uint8).reshape(height, width)
            self.pixels[row * ch:row * ch + height, col * cw:col * cw + width] = \
                tile[:self.meta.height - row * ch, :self.meta.width - col * cw]

    def grid(self, ts_ms: int):
        from foxglove_schemas_protobuf.Grid_pb2 import Grid
        from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField

        resolution = self.meta.resolution or 1.0
        ox, oy, _ = self.meta.origin or (0.0, 0.0, 0.0)
        grid = Grid(frame_id=MAP_FRAME, column_count=self.meta.width, row_stride=self.meta.width,
                    cell_stride=1, data=np.flipud(self.pixels).tobytes(),  # row 0 = bottom (+y up)
                    fields=[PackedElementField(name="value", offset=0,
                                               type=PackedElementField.NumericType.UINT8)])
        grid.timestamp.FromMilliseconds(ts_ms)
        grid.cell_size.x = grid.cell_size.y = resolution
        grid.pose.position.x, grid.pose.position.y = ox, oy
        grid.pose.orientation.w = 1.0
        return grid


def _pose_message(row: PoseRow):
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame

    message = PoseInFrame(frame_id=MAP_FRAME)
    message.timestamp.FromMilliseconds(row.ts_ms)
    p, q = message.pose.position, message.pose.orientation
    p.x, p.y, p.z = row.x, row.y, row.z
    q.x, q.y, q.z, q.w = row.qx, row.qy, row.qz, row.qw
    return message


def _all_poses(store: HistoryStore, from_ms: int, to_ms: int, page: int):
    """Every pose of the window, page by page (a page never splits one instant's robots)."""
    cursor = from_ms
    while cursor < to_ms:
        rows = store.poses(cursor, to_ms, None, page)
        if len(rows) < page:
            yield from rows
            return
        last = rows[-1].ts_ms
        if last == cursor:  # one instant fills a page: take it whole and move on
            yield from store.poses(cursor, cursor + 1, None, 10 * page)
            cursor += 1
            continue
        yield from (r for r in rows if r.ts_ms < last)
        cursor = last


def export_mcap(store: HistoryStore, from_ms: int, to_ms: int, out: BinaryIO, *,
                grid_every_ms: int = 10_000, page: int = 50_000) -> McapCounts:
    """Writes the window as MCAP: the map at `from_ms`, again after chunk changes (at most
    one grid per `grid_every_ms`, and the last state), and every pose. Returns the counts."""
    from mcap.writer import CompressionType
    from mcap_protobuf.writer import Writer

    meta = store.latest_meta()
    if meta is None:
        raise ValueError("no map geometry is set yet (the 2019 meta); nothing to export")
    counts = McapCounts()
    floor = _Floor(meta, store)
    floor.apply([(c.row, c.column, c.content_hash) for c in store.map_at(from_ms)])
    writer = Writer(out, compression=CompressionType.LZ4, profile="")

    def write_grid(ts_ms: int) -> None:
        writer.write_message(MAP_TOPIC, floor.grid(ts_ms), log_time=ts_ms * 1_000_000,
                             publish_time=ts_ms * 1_000_000)
        counts.grids += 1

    write_grid(from_ms)
    changes = store.chunk_events(from_ms, to_ms, limit=1_000_000)
    poses = _all_poses(store, from_ms, to_ms, page)
    pending: list[tuple[int, int, str]] = []
    last_grid_ms = from_ms
    next_pose = next(poses, None)
    for change in changes + [None]:
        # Poses up to this change's time first: MCAP readers like log times in order.
        until = change.ts_ms if change is not None else to_ms
        while next_pose is not None and next_pose.ts_ms < until:
            if pending and next_pose.ts_ms - last_grid_ms >= grid_every_ms:
                floor.apply(pending)
                pending = []
                last_grid_ms = next_pose.ts_ms
                write_grid(last_grid_ms)
            writer.write_message(pose_topic(next_pose.robot_id), _pose_message(next_pose),
                                 log_time=next_pose.ts_ms * 1_000_000,
                                 publish_time=next_pose.ts_ms * 1_000_000)
            counts.poses += 1
            next_pose = next(poses, None)
        if change is None:
            break
        pending.append((change.row, change.column, change.content_hash))
        counts.chunk_changes += 1
        if change.ts_ms - last_grid_ms >= grid_every_ms:
            floor.apply(pending)
            pending = []
            last_grid_ms = change.ts_ms
            write_grid(last_grid_ms)
    if pending:
        floor.apply(pending)
        write_grid(max(last_grid_ms, to_ms - 1))
    writer.finish()
    return counts
