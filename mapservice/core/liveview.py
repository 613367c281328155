"""The live views' rules, as pure functions (the processors hold the state, `processors/views.py`).

Latest map: per chunk, the write with the greatest (event time, robot id) seen so far, the
order `timetravel.fold_map` uses. As in the 2019 service, an older write does not
replace the live version (it is still history, and the map at its time shows it); a
re-delivered write is not a change either. Each change is advertised once, in the 2019
shape of appendix A.1.3.

Robots: per robot, its pose with the greatest event time and when it was last heard
from (the greatest receive time); online while that is at most `robot_offline_after_s`
old. A pose's clock skew is receive time minus event time; beyond the threshold it is
flagged (the 2019 document's idea I.3).
"""

from __future__ import annotations

import base64
import threading
from collections.abc import Iterable
from typing import Any

import msgspec
from cachetools import LRUCache, cached

from mapservice.core.events import ChunkUpdated, Envelope, pose_of
from mapservice.core.legacy_query import chunk_id
from mapservice.core.ports import ChunkState
from mapservice.core.render import chunk_pixels, png
from mapservice.core.timetravel import chunk_order
from mapservice.core.wire2019 import format_timestamp


def chunk_state(e: Envelope) -> ChunkState:
    p = e.payload
    assert isinstance(p, ChunkUpdated)
    return ChunkState(p.row, p.column, e.event_time_ms, e.robot_id, p.content_hash.hex())


def supersedes(new: ChunkState, current: ChunkState | None) -> bool:
    """Does `new` become the live version of its chunk?"""
    return current is None or chunk_order(new) > chunk_order(current)


def apply_chunks(
    view: dict[tuple[int, int], ChunkState], events: Iterable[Envelope]
) -> list[Envelope]:
    """Folds chunk writes into `view` (in place); returns, per chunk that changed, the
    write that is live now (in the batch's order), i.e. what to advertise."""
    changed: dict[tuple[int, int], Envelope] = {}
    for e in events:
        if not isinstance(e.payload, ChunkUpdated):
            continue
        state = chunk_state(e)
        key = (state.row, state.column)
        if supersedes(state, view.get(key)):
            view[key] = state
            changed[key] = e
    return list(changed.values())


def chunk_id_2019(row: int, column: int, ts_ms: int) -> str:
    """The 2019 chunk id, `row:3_column:2_2018-12-20T23:34:33` (listing 11), as the
    chunk service parses it."""
    return chunk_id(row, column, format_timestamp(ts_ms))


# Base64 of the zlib data and of the PNG, by content hash: rendering a PNG is ~2 ms, and
# maps repeat contents (a pallet moved back, a chunk re-sent unchanged by another robot).
# ~1,000 entries of ~25 KB each.
@cached(LRUCache(maxsize=1024), key=lambda p: p.content_hash, lock=threading.Lock())
def _encoded(p: ChunkUpdated) -> tuple[str, str]:
    return (
        base64.b64encode(p.data).decode(),
        base64.b64encode(png(chunk_pixels(p.width, p.height, p.data))).decode(),
    )


def advertisement(e: Envelope, public_base_url: str) -> dict[str, Any]:
    """The 2019 advertisement (appendix A.1.3, listing 15) of a chunk write."""
    p = e.payload
    assert isinstance(p, ChunkUpdated)
    chunk_id = chunk_id_2019(p.row, p.column, e.event_time_ms)
    url = f"{public_base_url.rstrip('/')}/api/chunk-service/chunks/id/{chunk_id}"
    chunk_b64, png_b64 = _encoded(p)
    return {
        "row": p.row,
        "column": p.column,
        "robotId": e.robot_id,
        "chunk": chunk_b64,
        "png": png_b64,
        "timestamp": format_timestamp(e.event_time_ms),
        "id": chunk_id,
        "chunkUrl": url,
        "pngUrl": f"{url}/png",
    }


# --- robots ------------------------------------------------------------------------------


class RobotState(msgspec.Struct, frozen=True, gc=False):  # gc=False: core/ports.py says why
    robot_id: str
    ts_ms: int  # event time of its latest pose
    receive_time_ms: int  # that pose's receive time
    last_seen_ms: int  # the latest receive time of any of its poses
    position: tuple[float, float, float]
    battery_level: float | None
    charging: bool | str | None
    loaded: bool | str | None


def clock_skew_ms(receive_time_ms: int, ts_ms: int) -> int:
    return receive_time_ms - ts_ms


def skew_flagged(skew_ms: int, threshold_s: float) -> bool:
    return abs(skew_ms) > threshold_s * 1000


def is_online(age_ms: int, offline_after_s: float, connection: str | None = None) -> bool:
    """Heard from within `offline_after_s`, and not OFFLINE or CONNECTIONBROKEN by its
    latest connection state (a VDA 5050 vehicle's, where one holds)."""
    return age_ms <= offline_after_s * 1000 and connection not in OFF_STATES


# A VDA 5050 vehicle says it went OFFLINE, or its broker that the connection broke.
OFF_STATES = ("OFFLINE", "CONNECTIONBROKEN")
# A connection state holds this long at most as far as the robots at an instant go (as
# the replay's fleet panel reads them: the hour before the playhead).
CONNECTION_STATE_HOLDS_MS = 3_600_000


def apply_poses(view: dict[str, RobotState], events: Iterable[Envelope]) -> list[str]:
    """Folds poses into `view` (in place); returns the robots whose latest pose changed."""
    changed: dict[str, None] = {}
    for e in events:
        p = pose_of(e.payload)
        if p is None:
            continue
        current = view.get(e.robot_id)
        last_seen = max(e.receive_time_ms, current.last_seen_ms if current else e.receive_time_ms)
        if current is None or e.event_time_ms > current.ts_ms:
            view[e.robot_id] = RobotState(
                e.robot_id,
                e.event_time_ms,
                e.receive_time_ms,
                last_seen,
                p.position,
                p.battery_level,
                p.charging,
                p.loaded,
            )
            changed[e.robot_id] = None
        elif last_seen != current.last_seen_ms:
            view[e.robot_id] = msgspec.structs.replace(current, last_seen_ms=last_seen)
    return list(changed)


def online_robots(view: dict[str, RobotState], now_ms: int, offline_after_s: float) -> set[str]:
    return {r for r, s in view.items() if is_online(now_ms - s.last_seen_ms, offline_after_s)}
