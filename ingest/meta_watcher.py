"""Follows the map-meta topic so validation knows the grid (rows, columns, chunk size)."""

from __future__ import annotations

import threading

import structlog
from confluent_kafka import OFFSET_BEGINNING, Consumer, TopicPartition

from mapservice.core.events import MapMetaSet, decode
from mapservice.settings import Settings

log = structlog.get_logger(__name__)


class MetaWatcher:
    """Reads the whole meta topic from the beginning (assign, no consumer group)."""

    def __init__(self, settings: Settings, on_meta) -> None:
        self.settings = settings
        self.on_meta = on_meta
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.newest_ms = -1

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="meta-watcher", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread:
            self._thread.join(timeout=5)

    def _run(self) -> None:
        topic = self.settings.topic_meta_events
        consumer = Consumer({**self.settings.kafka_config(), "group.id": "mapservice-meta-watcher",
                             "enable.auto.commit": False})
        try:
            md = consumer.list_topics(topic, timeout=30)
            parts = sorted(md.topics[topic].partitions) if topic in md.topics else [0]
            consumer.assign([TopicPartition(topic, p, OFFSET_BEGINNING) for p in parts])
            while not self._stop.is_set():
                msg = consumer.poll(0.5)
                if msg is None or msg.error():
                    continue
                try:
                    env = decode(msg.value())
                except Exception as exc:  # a foreign record must not stop the watcher
                    log.warning("meta record undecodable", error=str(exc))
                    continue
                if isinstance(env.payload, MapMetaSet) and env.event_time_ms >= self.newest_ms:
                    self.newest_ms = env.event_time_ms
                    self.on_meta(env.payload)
                    log.info("map meta applied", rows=env.payload.chunk_rows,
                             cols=env.payload.chunk_cols, chunk_width=env.payload.chunk_width)
        except Exception:
            log.exception("meta watcher failed; validating with the default grid")
        finally:
            consumer.close()
