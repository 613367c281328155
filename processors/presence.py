"""The robots as the live views know them: each one's latest state, and who is online
(heard from within robot_offline_after_s), logged as robots come and go."""

from __future__ import annotations

from collections.abc import Sequence

import structlog
from prometheus_client import Gauge

from mapservice.core.events import Envelope
from mapservice.core.liveview import RobotState, apply_poses, online_robots
from mapservice.core.ports import TimeTravelReader

log = structlog.get_logger(__name__)

ROBOTS_ONLINE = Gauge("mapservice_robots_online", "Robots heard from within robot_offline_after_s")


class Presence:
    def __init__(self, offline_after_s: float) -> None:
        self.offline_after_s = offline_after_s
        self.robots: dict[str, RobotState] = {}
        self.online: set[str] = set()

    def load(self, history: TimeTravelReader, horizon_ms: int) -> None:
        """Each robot's latest stored pose (blocking: run in the store's thread)."""
        self.robots = {
            p.robot_id: RobotState(
                p.robot_id,
                p.ts_ms,
                p.receive_time_ms,
                p.receive_time_ms,
                (p.x, p.y, p.z),
                p.battery_level,
                p.charging,
                p.loaded,
            )
            for p in history.robots_at(horizon_ms)
        }

    def apply(self, events: Sequence[Envelope]) -> None:
        apply_poses(self.robots, events)

    def check(self, now_ms: int) -> tuple[set[str], set[str]]:
        """Logs robots going online/offline; returns (came online, went offline)."""
        online = online_robots(self.robots, now_ms, self.offline_after_s)
        came, went = online - self.online, self.online - online
        for robot in sorted(came):
            log.info("robot online", robot=robot)
        for robot in sorted(went):
            state = self.robots.get(robot)  # gone from a rebuilt view if its history is
            log.info(
                "robot offline",
                robot=robot,
                silent_s=None if state is None else round((now_ms - state.last_seen_ms) / 1000, 1),
            )
        self.online = online
        ROBOTS_ONLINE.set(len(online))
        return came, went
