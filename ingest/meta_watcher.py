"""Follows the map-meta topic so validation knows the grid (rows, columns, chunk size)."""

from __future__ import annotations

from collections.abc import Callable

import structlog
from confluent_kafka import OFFSET_BEGINNING, Consumer, TopicPartition

from mapservice.core.events import MapMetaSet, decode
from mapservice.settings import Settings

from .topic_follower import TopicFollower

log = structlog.get_logger(__name__)


class MetaWatcher(TopicFollower):
    """Reads the whole meta topic from the beginning (assign, no consumer group)."""

    thread_name = "meta-watcher"
    group_id = "mapservice-meta-watcher"
    poll_s = 0.5

    def __init__(self, settings: Settings, on_meta: Callable[[MapMetaSet], object]) -> None:
        super().__init__(settings, settings.topic_meta_events)
        self.on_meta = on_meta
        self.newest_ms = -1

    def _run(self) -> None:
        """One read: a failure leaves the gateway validating with the grid it has."""
        try:
            self._read()
        except Exception:
            log.exception("meta watcher failed; validating with the default grid")

    def _start_offsets(self, consumer: Consumer, partitions: list[int]) -> list[TopicPartition]:
        return [TopicPartition(self.topic, p, OFFSET_BEGINNING) for p in partitions]

    def _on_record(self, value: bytes | None) -> None:
        if value is None:
            log.warning("meta record undecodable", error="a tombstone (no value)")
            return
        try:
            env = decode(value)
        except Exception as exc:  # a foreign record must not stop the watcher
            log.warning("meta record undecodable", error=str(exc))
            return
        if isinstance(env.payload, MapMetaSet) and env.event_time_ms >= self.newest_ms:
            self.newest_ms = env.event_time_ms
            self.on_meta(env.payload)
            log.info(
                "map meta applied",
                rows=env.payload.chunk_rows,
                cols=env.payload.chunk_cols,
                chunk_width=env.payload.chunk_width,
            )
