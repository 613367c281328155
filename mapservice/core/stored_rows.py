"""Events as the store keeps them: what a reader of the store gets back for an event
just stored, for the parts that compare the two (the live incident detection, the memory
store)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mapservice.core.events import Envelope, pose_of
from mapservice.core.ports import PoseRow


def stored_mm(v: float) -> float:
    """A position as the store keeps it: to the millimetre."""
    return round(v * 1000) / 1000


def stored_f32(v: float | None) -> float | None:
    """A quaternion component or battery level as the store keeps it: a 32-bit float."""
    return None if v is None else float(np.float32(v))


def pose_rows_of(events: Sequence[Envelope]) -> list[PoseRow]:
    """The poses among `events` (robots' own and VDA 5050 vehicles' on a known map), as the
    store keeps them: positions to the millimetre, quaternions and battery 32-bit."""
    rows = []
    for e in events:
        if (pose := pose_of(e.payload)) is not None:
            x, y, z = pose.position
            qx, qy, qz, qw = (float(np.float32(v)) for v in pose.orientation)
            path = (
                None
                if pose.path is None
                else tuple((stored_mm(a), stored_mm(b)) for a, b in pose.path)
            )
            rows.append(
                PoseRow(
                    e.robot_id,
                    e.event_time_ms,
                    stored_mm(x),
                    stored_mm(y),
                    stored_mm(z),
                    qx,
                    qy,
                    qz,
                    qw,
                    stored_f32(pose.battery_level),
                    pose.charging,
                    pose.loaded,
                    path,
                    e.receive_time_ms,
                )
            )
    return rows
