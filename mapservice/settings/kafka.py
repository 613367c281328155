"""Kafka: the brokers and how to reach them, the embedded broker of `mapservice up`, topics."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, Field, SecretStr


class KafkaSettings(BaseModel):
    """The Kafka clients' connection, security and tuning, the embedded broker and the topics."""

    kafka_bootstrap: str = Field("127.0.0.1:9092", description="Kafka bootstrap servers.")
    kafka_security_protocol: str = "PLAINTEXT"
    kafka_sasl_mechanism: str | None = None
    kafka_username: str | None = None
    kafka_password: SecretStr | None = None
    kafka_ssl_ca_file: Path | None = Field(
        None,
        description="CA bundle (PEM) that signs the brokers' certificates, for SSL/SASL_SSL "
        "(e.g. Strimzi's <cluster>-cluster-ca-cert); empty: the system's CAs.",
    )
    kafka_ssl_cert_file: Path | None = Field(
        None,
        description=(
            "Client certificate (PEM) the service presents to the brokers with SSL/SASL_SSL (mutual "
            "TLS, e.g. a Strimzi KafkaUser of type tls); needs MAPSERVICE_KAFKA_SSL_KEY_FILE."
        ),
    )
    kafka_ssl_key_file: Path | None = Field(
        None, description=("Private key (PEM, unencrypted) of MAPSERVICE_KAFKA_SSL_CERT_FILE.")
    )
    kafka_partitions: int = Field(6, ge=1, description="Partitions of topics the service creates.")
    kafka_replication: int = Field(1, ge=1)
    kafka_rebalance_timeout_s: float = Field(
        3.0, gt=0, description="Consumer-group rebalance timeout."
    )
    kafka_session_timeout_s: float = Field(
        10.0,
        ge=3,  # three heartbeats (one a second)
        description=(
            "Consumer-group session timeout of the processors' classic-protocol consumers: how "
            "long after a replica died (no heartbeat) its partitions go to the others or to "
            "its restart. At least the rebalance timeout; Apache Kafka refuses less than its "
            "group.min.session.timeout.ms (6 s by default, 3 s on the embedded node)."
        ),
    )
    kafka_check_ttl_s: float = Field(
        5.0,
        ge=0.5,
        le=60,
        description=(
            "How long the gateway's and the processors' readiness reuse an answer about Kafka "
            "(a broker metadata request at most this often): also how long a Kafka that went "
            "or came back may go unnoticed by /readyz."
        ),
    )
    kafka_group_protocol: Literal["classic", "consumer"] = Field(
        "classic",
        description=(
            "Consumer group protocol of the history consumer (librdkafka group.protocol): "
            "`classic` (join/sync rebalances; every Kafka, tansu too) or `consumer` (Kafka 4's "
            "KIP-848: the broker assigns partitions and holds the members' session timeout and "
            "heartbeat as group.consumer.* broker configs; Apache Kafka 4 only)."
        ),
    )
    kafka_linger_ms: int = Field(
        50,
        ge=0,
        le=1_000,
        description="How long the gateway's and "
        "the 2019 API's producer collects records into one batch per "
        "partition (librdkafka linger.ms).",
    )
    kafka_fetch_wait_ms: int = Field(
        500,
        ge=1,
        le=10_000,
        description="Longest the history's and the live relay's fetch waits for new records "
        "(librdkafka fetch.wait.max.ms). Apache Kafka answers as soon as records arrive, so "
        "the wait costs no latency there, and a short one only costs idle fetches; tansu "
        "answers only when it runs out, so the embedded tansu runs with 50 ms.",
    )
    # The broker `mapservice up` and the test stacks embed (mapservice/local/kafka_broker.py).
    embedded_kafka: Literal["auto", "apache", "tansu"] = Field(
        "auto",
        description=(
            "Kafka broker `mapservice up` embeds: `apache` (one KRaft node from the Apache Kafka "
            "jars, log on disk in DATA_DIR/kafka/), `tansu` (in memory: no retention, a restart "
            "loses every record), `auto`: apache where Java is installed, else tansu."
        ),
    )
    embedded_kafka_heap_mb: int = Field(
        256, ge=128, le=8192, description=("Java heap of the embedded Apache Kafka (-Xmx).")
    )
    embedded_kafka_metadata_idle_ms: int = Field(
        5000,
        ge=0,
        le=60_000,
        description=(
            "How often the embedded Apache Kafka's controller appends a no-op record to its "
            "metadata log while the metadata stand still (metadata.max.idle.interval.ms; 0: "
            "never). Kafka's 500 ms costs an idle node a flushed append twice a second."
        ),
    )
    embedded_kafka_retention_hours: int = Field(
        24,
        ge=1,
        le=24 * 24,
        description=(
            "How long the embedded Apache Kafka keeps records (log.retention.hours); everything is "
            "in ClickHouse within seconds."
        ),
    )
    embedded_kafka_retention_bytes: int = Field(
        256 * 1024**2,
        ge=16 * 1024**2,
        description=(
            "Most bytes the embedded Apache Kafka keeps per partition (log.retention.bytes)."
        ),
    )
    kafka_jars_dir: Path | None = Field(
        None,
        description=(
            "Where Maven puts the embedded Apache Kafka's jars; empty: "
            "~/.cache/mapservice/kafka-<version>/ (XDG_CACHE_HOME respected)."
        ),
    )
    topic_chunk_events: str = "mapservice.chunk-events.v1"
    topic_pose_events: str = "mapservice.pose-events.v1"
    topic_meta_events: str = "mapservice.meta-events.v1"
    topic_dead_letter: str = "mapservice.dead-letter.v1"
    topic_annotation_events: str = Field(
        "mapservice.annotation-events.v1",
        description=(
            "Operators' annotation edits (points of interest, zones), keyed by annotation and "
            "compacted: each annotation's latest edit stays."
        ),
    )
    topic_command_events: str = Field(
        "mapservice.command-events.v1",
        description=(
            "Operators' commands to robots and the robots' acks and outcomes, keyed by robot "
            "(history: kept as long as the ClickHouse history)."
        ),
    )
    topic_live: str = Field(
        "mapservice.live.v1",
        description="Stored events' live messages, "
        "processors -> every API process (WebSocket /api/v1/live).",
    )
    live_retention_s: int = Field(
        3600,
        ge=60,
        description="Retention of the live topic when the "
        "service creates it (readers start at its end; short is fine).",
    )

    def kafka_config(self) -> dict[str, str]:
        """librdkafka settings shared by every confluent-kafka client of the service."""
        conf: dict[str, str] = {
            "bootstrap.servers": self.kafka_bootstrap,
            "security.protocol": self.kafka_security_protocol,
        }
        if self.kafka_sasl_mechanism:
            conf["sasl.mechanism"] = self.kafka_sasl_mechanism
        if self.kafka_username:
            conf["sasl.username"] = self.kafka_username
        if self.kafka_password:
            conf["sasl.password"] = self.kafka_password.get_secret_value()
        if self.kafka_ssl_ca_file:
            conf["ssl.ca.location"] = str(self.kafka_ssl_ca_file)
        if self.kafka_ssl_cert_file and self.kafka_ssl_key_file:
            conf["ssl.certificate.location"] = str(self.kafka_ssl_cert_file)
            conf["ssl.key.location"] = str(self.kafka_ssl_key_file)
        return conf

    @property
    def kafka_topics(self) -> list[str]:
        return [
            self.topic_chunk_events,
            self.topic_pose_events,
            self.topic_meta_events,
            self.topic_dead_letter,
            self.topic_live,
            self.topic_annotation_events,
            self.topic_command_events,
        ]
