"""The long-running processes keep the cyclic collector's full collections short."""

from __future__ import annotations

import gc

from mapservice.core.events import ChunkUpdated, Envelope, PoseReported
from mapservice.core.liveview import RobotState
from mapservice.core.ports import ChunkRow, ConflictRow, PoseRow
from mapservice.runtime.heap import freeze_startup_heap


def test_the_records_held_by_the_thousand_are_not_tracked_by_the_collector() -> None:
    """Events, their payloads and the store's rows are invisible to the cyclic GC."""
    pose = PoseReported((1.0, 2.0, 0.0), (0.0, 0.0, 0.0, 1.0), path=((1.0, 2.0),))
    records = [
        pose,
        ChunkUpdated(0, 0, 8, 8, b"x", b"h"),
        Envelope("e", "pose.reported", 1, "robot-1", 1, 2, pose),
        ChunkRow(0, 0, 1, "robot-1", "ab", 2),
        ConflictRow(0, 0, 2, "a", 1, "b"),
        PoseRow("robot-1", 1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, None, None, None, None, 2),
        RobotState("robot-1", 1, 2, 2, (0.0, 0.0, 0.0), None, None, None),
    ]
    assert [type(r).__name__ for r in records if gc.is_tracked(r)] == []


def test_what_start_up_built_is_frozen_out_of_later_collections() -> None:
    """freeze_startup_heap moves every live object to the permanent generation."""
    thresholds = gc.get_threshold()
    try:
        frozen = freeze_startup_heap()
        assert frozen > 10_000
        # The collector's generations are empty but for what other threads (a test run's
        # clients and brokers' readers) allocated since; the count of frozen objects itself
        # moves when those threads free one of them.
        assert len(gc.get_objects()) < frozen // 100
    finally:
        gc.unfreeze()
        gc.set_threshold(*thresholds)


def test_after_start_up_a_young_collection_waits_for_10000_more_objects() -> None:
    """freeze_startup_heap raises the young generation's threshold from 700 to 10,000."""
    thresholds = gc.get_threshold()
    try:
        freeze_startup_heap()
        assert gc.get_threshold() == (10_000, 10, 10)
    finally:
        gc.unfreeze()
        gc.set_threshold(*thresholds)
