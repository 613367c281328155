"""One embedded Apache Kafka node's configuration: where it listens and keeps its log,
what it keeps, and the files its JVM reads (server.properties, log4j2.yaml)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from mapservice.local.kafka_auth import listener_properties, sasl_client_config

NODE_ID = 1
# WARN and above, plus the lines that say the node started and stopped.
LOG4J2_YAML = """\
Configuration:
  Appenders:
    Console:
      name: STDOUT
      PatternLayout:
        pattern: "[%d] %p %m (%c)%n"
  Loggers:
    Root:
      level: WARN
      AppenderRef:
        - ref: STDOUT
    Logger:
      - name: kafka.server.KafkaRaftServer
        level: INFO
"""


@dataclass(frozen=True)
class KafkaNodeConfig:
    """One KRaft node on 127.0.0.1: where it listens and keeps its log, what it keeps. Alone
    by default; with `voters` and `replication` one of a cluster (the fault tests')."""

    log_dir: Path
    port: int
    controller_port: int
    heap_mb: int = 256
    retention_hours: int = 24
    # Per partition; log segments of a sixteenth of it, so retention frees space in steps.
    retention_bytes: int = 256 * 1024**2
    node_id: int = NODE_ID
    voters: str = ""  # id@host:port,...; empty: this node alone
    replication: int = 1  # of internal and new topics
    min_insync_replicas: int = 1
    # How often the controller appends a no-op record to the metadata log while nothing
    # else changes it (metadata.max.idle.interval.ms; Kafka's default 500 ms).
    metadata_idle_ms: int = 5000
    # (username, password) pairs: both listeners then take only SASL/PLAIN clients that
    # name one of them (kafka_auth.py); the first is the node's own, for its controller
    # connection. Empty: no authentication (anyone who reaches the port may produce).
    sasl_users: tuple[tuple[str, str], ...] = ()

    def properties(self) -> str:
        segment = max(1024**2, self.retention_bytes // 16)
        return "\n".join(
            [
                "process.roles=broker,controller",
                f"node.id={self.node_id}",
                # A static voter set: the controller's port is not written into the metadata
                # log, so a lone node's restart may pick another free port.
                "controller.quorum.voters="
                + (self.voters or f"{self.node_id}@127.0.0.1:{self.controller_port}"),
                *listener_properties(self.port, self.controller_port, self.sasl_users),
                f"log.dirs={self.log_dir}",
                "num.partitions=1",
                f"default.replication.factor={self.replication}",
                f"min.insync.replicas={self.min_insync_replicas}",
                f"offsets.topic.replication.factor={self.replication}",
                "offsets.topic.num.partitions=6",
                f"transaction.state.log.replication.factor={self.replication}",
                f"transaction.state.log.min.isr={self.min_insync_replicas}",
                f"share.coordinator.state.topic.replication.factor={self.replication}",
                f"share.coordinator.state.topic.min.isr={self.min_insync_replicas}",
                "group.initial.rebalance.delay.ms=0",
                # Classic-protocol members may ask for sessions down to 3 s
                # (MAPSERVICE_KAFKA_SESSION_TIMEOUT_S; Kafka's floor is 6 s).
                "group.min.session.timeout.ms=3000",
                # Consumer groups of Kafka 4's protocol (KIP-848, MAPSERVICE_KAFKA_GROUP_PROTOCOL):
                # the broker holds the members' session and heartbeat; the same 10 s and 1 s the
                # classic protocol's members ask for (kafka_batch_source.py), under Kafka's
                # defaults' floors of 45 s and 5 s.
                "group.consumer.min.session.timeout.ms=10000",
                "group.consumer.session.timeout.ms=10000",
                "group.consumer.min.heartbeat.interval.ms=1000",
                "group.consumer.heartbeat.interval.ms=1000",
                # The service creates its own topics (the meta topic compacted).
                "auto.create.topics.enable=false",
                # Everything is in ClickHouse within a second: Kafka keeps a day, and at most
                # retention_bytes per partition, checked every minute.
                f"log.retention.hours={self.retention_hours}",
                f"log.retention.bytes={self.retention_bytes}",
                f"log.segment.bytes={segment}",
                "log.retention.check.interval.ms=60000",
                # After a SIGKILL the restarted node may register only once its old session has
                # expired (9 s by default); heartbeats stay in this one process.
                "broker.heartbeat.interval.ms=1000",
                "broker.session.timeout.ms=4000",
                # An idle controller otherwise appends (and flushes) a no-op record to the
                # metadata log twice a second, and the broker applies each one: a fixed cost
                # that follows time, not work. Nothing of one node waits for them.
                f"metadata.max.idle.interval.ms={self.metadata_idle_ms}",
                # Few threads: one small node on a shared machine.
                "num.network.threads=2",
                "num.io.threads=2",
                "background.threads=2",
                "num.recovery.threads.per.data.dir=1",
                "",
            ]
        )

    def client_config(self) -> dict[str, str]:
        """librdkafka's security settings to reach this node (as its own user)."""
        if not self.sasl_users:
            return {}
        return sasl_client_config(*self.sasl_users[0])

    def write_files(self) -> Path:
        """Its server.properties and log4j2.yaml, beside its log directory; the former's path."""
        config_dir = self.log_dir.parent
        config_dir.mkdir(parents=True, exist_ok=True)
        config_file = config_dir / "server.properties"
        # Only this user reads it: with SASL it holds the users' passwords.
        with open(os.open(config_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600), "w") as file:
            file.write(self.properties())
        config_file.chmod(0o600)
        (config_dir / "log4j2.yaml").write_text(LOG4J2_YAML)
        return config_file
