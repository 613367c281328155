"""Creates the service's Kafka topics (tansu does not auto-create; production may not)."""

from __future__ import annotations

import time

import structlog
from confluent_kafka.admin import AdminClient, NewTopic

from mapservice.settings import Settings

log = structlog.get_logger(__name__)


def topic_partitions(settings: Settings, topic: str) -> int:
    # The meta topic is one ordered stream; the live topic is one partition so that each
    # processor's batches reach the API in the order they were stored (its volume is a
    # few hundred small records a second at 1,000 robots).
    if topic in (settings.topic_meta_events, settings.topic_live):
        return 1
    return settings.kafka_partitions


def topic_config(settings: Settings, topic: str) -> dict[str, str]:
    """What the service creates each topic with; infra/k8s/strimzi-topics.yaml declares the
    same (tests/infra/test_manifest_components.py compares them). Events and dead letters
    are kept as long as the ClickHouse history, the meta stream is compacted (the latest
    meta stays), the live topic keeps an hour, the annotation edits are compacted by
    annotation (the floor's zones outlive any retention). With replicas, a write needs all but one of them."""
    if topic in (settings.topic_meta_events, settings.topic_annotation_events):
        config = {"cleanup.policy": "compact"}
    elif topic == settings.topic_live:
        config = {"cleanup.policy": "delete", "retention.ms": str(settings.live_retention_s * 1000)}
    else:
        config = {"cleanup.policy": "delete", "retention.ms": str(settings.retention_ms)}
    if settings.kafka_replication > 1:
        config["min.insync.replicas"] = str(settings.kafka_replication - 1)
    return config


def ensure_topics(settings: Settings, timeout_s: float = 60.0) -> list[str]:
    """Idempotent; waits for the broker. Returns the topics it created."""
    admin = AdminClient(settings.kafka_config())
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            existing = set(admin.list_topics(timeout=5).topics)
            break
        except Exception as exc:
            if time.monotonic() > deadline:
                raise RuntimeError(
                    f"Kafka at {settings.kafka_bootstrap} did not answer in {timeout_s:.0f} s; "
                    "check MAPSERVICE_KAFKA_BOOTSTRAP"
                ) from exc
            time.sleep(0.5)
    wanted = [t for t in settings.kafka_topics if t not in existing]
    if not wanted:
        return []
    futures = admin.create_topics(
        [
            NewTopic(
                t,
                num_partitions=topic_partitions(settings, t),
                replication_factor=settings.kafka_replication,
                config=topic_config(settings, t),
            )
            for t in wanted
        ]
    )
    created = []
    for topic, fut in futures.items():
        try:
            fut.result(timeout=30)
            created.append(topic)
        except Exception as exc:
            if "TOPIC_ALREADY_EXISTS" not in str(exc):
                raise
    log.info("kafka topics created", topics=created)
    return created
