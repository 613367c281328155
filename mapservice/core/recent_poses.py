"""The robots' recent poses as columns, kept up to date batch by batch, for the near-miss
rule (near_miss.py) of the live detection: the columns `pose_columns` gives for every
robot's poses from an instant on (each robot's newest before it included), without walking
every robot's track on every batch: a batch's poses are added as they come (late ones and
redelivered ones too), and each read sorts the few seconds held once, in arrays."""

from __future__ import annotations

import bisect
from collections.abc import Sequence
from operator import attrgetter

import numpy as np

from mapservice.core.near_miss import PoseColumns, pose_columns
from mapservice.core.ports import PoseRow


class RecentPoses:
    def __init__(self) -> None:
        # Every pose given since this instant, and each robot's newest before it; None: to
        # be built from the tracks at the next read.
        self.from_ms: int | None = None
        self.names: list[str] = []  # a robot's index -> its id
        self.index: dict[str, int] = {}
        # the robots' indexes in the order of their ids, and each one's place in it
        self.by_name: list[int] = []
        self.rank = np.zeros(0, np.int64)
        self.robot = np.zeros(0, np.int64)
        self.ts = np.zeros(0, np.int64)
        self.x = np.zeros(0, np.float64)
        self.y = np.zeros(0, np.float64)
        self.pending: list[Sequence[PoseRow]] = []

    def reset(self) -> None:
        """Forgets all: the next read builds from the tracks."""
        self.from_ms = None
        self.pending.clear()

    def add(self, poses: Sequence[PoseRow]) -> None:
        """Poses as they are stored (a pose at an instant already given replaces it)."""
        if self.from_ms is not None:
            self.pending.append(poses)

    def columns(self, from_ms: int, tracks: dict[str, list[PoseRow]]) -> PoseColumns:
        """As `pose_columns` of every robot's poses from `from_ms` on, with its newest
        before: `tracks` (every robot's stored poses, in time order, one per instant) must
        hold those, and all poses given to `add` since the last read."""
        if self.from_ms is None or from_ms < self.from_ms:
            self._build(from_ms, tracks)
        else:
            self._take_pending()
        if len(self.rank) != len(self.names):
            self.by_name = sorted(range(len(self.names)), key=self.names.__getitem__)
            self.rank = np.empty(len(self.by_name), dtype=np.int64)
            self.rank[self.by_name] = np.arange(len(self.by_name))
        ts = self.ts
        # by robot (by id), then time; of two poses of a robot at one instant, the last given
        order = np.lexsort((np.arange(len(ts)), ts, self.rank[self.robot]))
        robot, ts, x, y = self.robot[order], ts[order], self.x[order], self.y[order]
        same_next = np.zeros(len(ts), dtype=bool)
        same_next[:-1] = robot[1:] == robot[:-1]
        later = np.ones(len(ts), dtype=bool)
        later[:-1] = ts[1:] != ts[:-1]
        before_next = np.zeros(len(ts), dtype=bool)
        before_next[:-1] = ts[1:] < from_ms
        # a robot's newest pose, and each one that the next (not at its instant) follows
        # from from_ms on: the newest before from_ms and all after
        keep = ~same_next | (later & ~before_next)
        self.robot, self.ts, self.x, self.y = robot[keep], ts[keep], x[keep], y[keep]
        self.from_ms = from_ms
        return PoseColumns(
            [self.names[k] for k in self.by_name], self.rank[self.robot], self.ts, self.x, self.y
        )

    def _build(self, from_ms: int, tracks: dict[str, list[PoseRow]]) -> None:
        since = {
            r: track[max(0, bisect.bisect_left(track, from_ms, key=_ts) - 1) :]
            for r, track in tracks.items()
        }
        cols = pose_columns(since)
        self.names = list(cols.robots)
        self.index = {r: k for k, r in enumerate(self.names)}
        self.by_name = list(range(len(self.names)))
        self.rank = np.arange(len(self.names), dtype=np.int64)
        self.robot, self.ts, self.x, self.y = cols.robot, cols.ts, cols.x, cols.y
        self.pending.clear()

    def _take_pending(self) -> None:
        poses = [p for batch in self.pending for p in batch]
        self.pending.clear()
        if not poses:
            return
        for robot in set(map(attrgetter("robot_id"), poses)).difference(self.index):
            self.index[robot] = len(self.names)
            self.names.append(robot)
        n = len(poses)
        robot = map(self.index.__getitem__, map(attrgetter("robot_id"), poses))
        self.robot = np.concatenate((self.robot, np.fromiter(robot, np.int64, n)))
        ts = np.fromiter(map(attrgetter("ts_ms"), poses), np.int64, n)
        self.ts = np.concatenate((self.ts, ts))
        self.x = np.concatenate((self.x, np.fromiter(map(attrgetter("x"), poses), np.float64, n)))
        self.y = np.concatenate((self.y, np.fromiter(map(attrgetter("y"), poses), np.float64, n)))


def _ts(pose: PoseRow) -> int:
    return pose.ts_ms
