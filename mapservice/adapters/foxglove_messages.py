"""The messages of the Foxglove channels, built once for both readers of them: the MCAP
export (mcap_export.py) and the live and replay WebSocket server (foxglove_live.py,
foxglove_replay.py). The floor as a `foxglove.Grid`, a robot's pose (`foxglove.PoseInFrame`),
planned path (`foxglove.PosesInFrame`), its frame in the map (`foxglove.FrameTransform`) and
its state (JSON, mcap_channels.STATE_SCHEMA). Topic names and JSON schemas: mcap_channels.

May depend on: the ports (the floor reads chunk contents through `TimeTravelReader`)."""

from __future__ import annotations

import zlib
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

import numpy as np

from mapservice.adapters.mcap_channels import MAP_FRAME, battery_percent, robot_frame
from mapservice.core.events import MapMetaSet
from mapservice.core.ports import ChunkRow, PoseRow, TimeTravelReader

ROS_UNKNOWN = 205  # a cell no chunk covers yet (ROS map_server's grey)


class Floor:
    """The whole map as one image, updated chunk by chunk (contents read from the store by
    hash, each once). Writes are drawn when the image is next read, not as they come: a
    live floor nobody is shown costs a dict entry per write (decompressing and pasting a
    chunk costs about a hundred times that), and a cell written again before then is
    drawn once."""

    def __init__(self, meta: MapMetaSet, store: TimeTravelReader):
        self.meta, self.store = meta, store
        self._pixels = np.full((meta.height, meta.width), ROS_UNKNOWN, dtype=np.uint8)
        self._contents: dict[str, tuple[int, int, bytes]] = {}
        self._pending: dict[tuple[int, int], str] = {}  # (row, column) -> its newest hash

    def apply(self, changes: Iterable[tuple[int, int, str]]) -> None:
        """Takes each (row, column, content hash hex) in order (a later one wins)."""
        for row, col, digest in changes:
            self._pending[(row, col)] = digest

    @property
    def pixels(self) -> np.ndarray:
        """The image, every write taken so far drawn."""
        if self._pending:
            pending, self._pending = self._pending, {}
            self._draw(pending)
        return self._pixels

    def _draw(self, pending: Mapping[tuple[int, int], str]) -> None:
        missing = [bytes.fromhex(h) for h in set(pending.values()) if h not in self._contents]
        if missing:
            for stored_hash, stored in self.store.chunk_contents(missing).items():
                self._contents[stored_hash.hex()] = stored
        cw, ch = self.meta.chunk_width, self.meta.chunk_height
        for (row, col), digest in pending.items():
            content = self._contents.get(digest)
            if content is None:
                continue  # contents older than the retention: the chunk stays as it was
            width, height, data = content
            tile = np.frombuffer(zlib.decompress(data), dtype=np.uint8).reshape(height, width)
            self._pixels[row * ch : row * ch + height, col * cw : col * cw + width] = tile[
                : self.meta.height - row * ch, : self.meta.width - col * cw
            ]

    def reset(self) -> None:
        """Every cell unknown again (a seek draws the map at its instant from scratch)."""
        self._pending.clear()
        self._pixels.fill(ROS_UNKNOWN)

    def grid(self, ts_ms: int) -> Any:
        from foxglove_schemas_protobuf.Grid_pb2 import Grid
        from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField

        resolution = self.meta.resolution or 1.0
        ox, oy, _ = self.meta.origin or (0.0, 0.0, 0.0)
        grid = Grid(
            frame_id=MAP_FRAME,
            column_count=self.meta.width,
            row_stride=self.meta.width,
            cell_stride=1,
            data=np.flipud(self.pixels).tobytes(),  # row 0 = bottom (+y up)
            fields=[
                PackedElementField(
                    name="value", offset=0, type=PackedElementField.NumericType.UINT8
                )
            ],
        )
        grid.timestamp.FromMilliseconds(ts_ms)
        grid.cell_size.x = grid.cell_size.y = resolution
        grid.pose.position.x, grid.pose.position.y = ox, oy
        grid.pose.orientation.w = 1.0
        return grid


def pose_message(row: PoseRow) -> Any:
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame

    message = PoseInFrame(frame_id=MAP_FRAME)
    message.timestamp.FromMilliseconds(row.ts_ms)
    p, q = message.pose.position, message.pose.orientation
    p.x, p.y, p.z = row.x, row.y, row.z
    q.x, q.y, q.z, q.w = row.qx, row.qy, row.qz, row.qw
    return message


def path_message(row: PoseRow) -> Any:
    """The planned path as foxglove.PosesInFrame (what Foxglove's 3D panel draws as a line)."""
    from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame

    message = PosesInFrame(frame_id=MAP_FRAME)
    message.timestamp.FromMilliseconds(row.ts_ms)
    for x, y in row.path or ():
        pose = message.poses.add()
        pose.position.x, pose.position.y = x, y
        pose.orientation.w = 1.0
    return message


def transform_message(row: PoseRow) -> Any:
    """The robot's frame in the map (foxglove.FrameTransform): a 3D panel follows it, and
    anything drawn in the robot's frame moves with it."""
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform

    message = FrameTransform(parent_frame_id=MAP_FRAME, child_frame_id=robot_frame(row.robot_id))
    message.timestamp.FromMilliseconds(row.ts_ms)
    t, q = message.translation, message.rotation
    t.x, t.y, t.z = row.x, row.y, row.z
    q.x, q.y, q.z, q.w = row.qx, row.qy, row.qz, row.qw
    return message


def state_doc(row: PoseRow) -> dict[str, Any]:
    return {
        "battery_level": row.battery_level,
        "battery_percent": battery_percent(row.battery_level),
        "charging": row.charging,
        "loaded": row.loaded,
    }


def pose_row_of_live(message: Mapping[str, Any]) -> PoseRow:
    """A live pose message (core/live_messages.py) as the store's pose row."""
    x, y, z = (list(message["position"]) + [0.0, 0.0, 0.0])[:3]
    qx, qy, qz, qw = (list(message["orientation"]) + [0.0, 0.0, 0.0, 1.0])[:4]
    path = message.get("path")
    return PoseRow(
        robot_id=message["robotId"],
        ts_ms=int(message["ts_ms"]),
        x=float(x),
        y=float(y),
        z=float(z),
        qx=float(qx),
        qy=float(qy),
        qz=float(qz),
        qw=float(qw),
        battery_level=message.get("battery_level"),
        charging=message.get("charging"),
        loaded=message.get("loaded"),
        path=tuple((float(p[0]), float(p[1])) for p in path) if path else None,
        receive_time_ms=int(message.get("receive_time_ms", message["ts_ms"])),
    )


_PAGE = 50_000


def window_poses(
    store: TimeTravelReader, from_ms: int, to_ms: int, page: int = _PAGE
) -> Iterator[PoseRow]:
    """Every pose of [from_ms, to_ms) in time order, page by page (a page never splits
    one instant's robots)."""
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


def window_changes(
    store: TimeTravelReader, from_ms: int, to_ms: int, page: int = _PAGE
) -> list[ChunkRow]:
    """Every chunk write of [from_ms, to_ms) in event-time order (all of them: pages of
    `page` until one comes back short)."""
    out: list[ChunkRow] = []
    cursor = from_ms
    while cursor < to_ms:
        rows = store.chunk_events(cursor, to_ms, page)
        if len(rows) < page:
            return out + rows
        last = rows[-1].ts_ms
        if last == cursor:
            out += store.chunk_events(cursor, cursor + 1, 100 * page)
            cursor += 1
            continue
        out += [r for r in rows if r.ts_ms < last]
        cursor = last
    return out
