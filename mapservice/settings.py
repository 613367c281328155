"""One settings object per process, read from the environment (prefix ``MAPSERVICE_``)."""

from __future__ import annotations

import json
import re
from functools import cached_property
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

# The subtopics a VDA 5050 vehicle publishes (master control publishes order and instantActions).
VDA5050_SUBTOPICS = ("state", "visualization", "connection", "factsheet")

# The admin token the service had as its default until local mode generated one: a
# publicly known value, refused wherever it is still set in production.
DEFAULT_ADMIN_TOKEN = "local-admin-token"
DEFAULT_CLICKHOUSE_PASSWORD = ""
MIN_TOKEN_CHARS = 32  # `openssl rand -hex 32` gives 64; a 32-character hex token is 128 bits


def token_list(secret: SecretStr) -> list[str]:
    """The tokens of a comma- or whitespace-separated token setting (empty: none)."""
    return [t for t in re.split(r"[\s,]+", secret.get_secret_value()) if t]


def robot_tokens(secret: SecretStr) -> dict[str, str]:
    """`robotId=token` pairs of MAPSERVICE_API_ROBOT_TOKENS, token -> robotId."""
    pairs = {}
    for item in token_list(secret):
        robot_id, sep, token = item.partition("=")
        if not sep or not robot_id or not token:
            raise ValueError(
                "MAPSERVICE_API_ROBOT_TOKENS takes robotId=token pairs, "
                "comma-separated (e.g. agv-7=$(openssl rand -hex 32))"
            )
        pairs[token] = robot_id
    return pairs


class Settings(BaseSettings):
    """Everything a component needs to know; only addresses differ between modes."""

    model_config = SettingsConfigDict(env_prefix="MAPSERVICE_", extra="ignore")

    mode: Literal["local", "production"] = Field(
        "local", description="`production` refuses default secrets."
    )
    data_dir: Path = Field(Path(".mapservice-data"), description="Embedded mode's state.")
    log_level: str = "INFO"
    log_format: Literal["console", "json"] = "console"

    # Kafka
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
        50,
        ge=1,
        le=10_000,
        description="Longest a history fetch waits for new records (librdkafka fetch.wait.max.ms).",
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

    # ClickHouse: chdb:///dir (embedded) or http(s)://host:8123
    clickhouse_dsn: str = Field("", description="Empty means chdb:///<data_dir>/clickhouse.")
    clickhouse_database: str = "mapservice"
    clickhouse_username: str = "default"
    clickhouse_password: SecretStr = SecretStr(DEFAULT_CLICKHOUSE_PASSWORD)
    clickhouse_ca_file: Path | None = Field(
        None,
        description=(
            "CA bundle (PEM) that signs the ClickHouse server's certificate, for an https:// DSN; "
            "empty: the system's CAs."
        ),
    )
    clickhouse_cert_file: Path | None = Field(
        None,
        description=(
            "Client certificate (PEM) presented to ClickHouse over https (mutual TLS); needs "
            "MAPSERVICE_CLICKHOUSE_KEY_FILE."
        ),
    )
    clickhouse_key_file: Path | None = Field(
        None, description=("Private key (PEM, unencrypted) of MAPSERVICE_CLICKHOUSE_CERT_FILE.")
    )
    clickhouse_timeout_s: float = Field(
        60.0,
        gt=0,
        description=(
            "A request to a ClickHouse server that has not answered in this long fails and is "
            "retried (clickhouse-connect's own default, 300 s, let one hung insert stall the "
            "pipeline); not used by embedded chDB."
        ),
    )
    clickhouse_cluster: str = Field(
        "",
        description=(
            "A ClickHouse cluster name: schema statements run ON CLUSTER and tables are "
            "Replicated*MergeTree (one shard, N replicas). Empty: one server or chDB."
        ),
    )
    migrate_on_start: bool | None = Field(
        None,
        description=(
            "Apply schema migrations when a component starts. Empty: yes in local mode; no in "
            "production mode, where `mapservice migrate` runs once per release (a Job) and the "
            "components wait for the schema."
        ),
    )

    # Analysts: read-only SQL over the ClickHouse HTTP protocol at the API's /clickhouse
    analyst_username: str = Field("analyst", description="The read-only SQL user.")
    analyst_password: SecretStr = Field(
        SecretStr(""),
        description=(
            "Its password. Empty: generated on first start in local mode (DATA_DIR/secrets/"
            "analyst-password); analyst SQL is off in production mode."
        ),
    )
    analyst_max_execution_s: int = Field(30, ge=1, le=3600, description="Time limit per statement.")
    analyst_max_result_rows: int = Field(1_000_000, ge=1, description="Row limit per result.")
    analyst_max_memory_bytes: int = Field(
        2 * 1024**3,
        ge=64 * 1024**2,
        description=(
            "Memory limit per statement (at most ANALYST_MAX_MEMORY_TOTAL_BYTES / "
            "ANALYST_MAX_CONCURRENT_QUERIES)."
        ),
    )
    analyst_max_memory_total_bytes: int = Field(
        2 * 1024**3,
        ge=64 * 1024**2,
        description=(
            "Memory of all analysts' statements together: each runs with at most this divided "
            "by ANALYST_MAX_CONCURRENT_QUERIES."
        ),
    )
    analyst_max_concurrent_queries: int = Field(
        2,
        ge=1,
        le=64,
        description=(
            "Analysts' statements running at once, on threads of their own (not the API's)."
        ),
    )
    analyst_max_queued_queries: int = Field(
        8,
        ge=0,
        le=1000,
        description=(
            "Analysts' statements waiting for a thread; beyond them: HTTP 503 'too many "
            "queries' with Retry-After."
        ),
    )
    analyst_queue_timeout_s: float = Field(
        5.0,
        gt=0,
        le=600,
        description=("How long a waiting analyst statement waits for a thread before its 503."),
    )
    analyst_max_threads: int = Field(
        1,
        ge=1,
        le=64,
        description=(
            "Threads one analyst statement may use (ClickHouse max_threads): analysts together "
            "use at most ANALYST_MAX_CONCURRENT_QUERIES x this many cores."
        ),
    )

    # MQTT (topic names as in the 2019 configuration, appendix A.3)
    mqtt_url: str = Field("mqtt://127.0.0.1:1883", description="MQTT broker the gateway reads.")
    mqtt_ws_url: str = Field(
        "",
        description="The broker's MQTT-over-WebSocket URL as browsers "
        "reach it (the /controller page); empty: the page cannot publish.",
    )
    mqtt_username: str | None = None
    mqtt_password: SecretStr | None = None
    mqtt_ca_file: Path | None = Field(
        None,
        description=(
            "CA bundle (PEM) that signs the MQTT broker's certificate, with an mqtts:// URL; empty: "
            "the system's CAs."
        ),
    )
    mqtt_cert_file: Path | None = Field(
        None,
        description=(
            "Client certificate (PEM) presented to the MQTT broker with mqtts:// (mutual TLS); "
            "needs MAPSERVICE_MQTT_KEY_FILE."
        ),
    )
    mqtt_key_file: Path | None = Field(
        None, description=("Private key (PEM, unencrypted) of MAPSERVICE_MQTT_CERT_FILE.")
    )
    mqtt_client_id: str = Field(
        "mapservice-gateway", description="Stable: keeps the QoS 1 session."
    )
    mqtt_share_group: str = Field("", description="Non-empty: subscribe via $share/<group>/.")
    emqx_api_url: str = Field(
        "",
        description=(
            "EMQX's REST API (the dashboard port, e.g. http://emqx-dashboard.emqx:18083) for "
            "`mapservice robot add|remove|list --emqx`; only that command reads it."
        ),
    )
    emqx_api_key: str = Field("", description="EMQX API key (dashboard: System -> API Key).")
    emqx_api_secret: SecretStr = Field(SecretStr(""), description="Its secret.")
    create_chunk_topic: str = Field(
        "iot/chunks/create",
        description=(
            "2019 CREATE_CHUNK_TOPIC (carries no robot id: under MQTT authentication the broker's "
            "ACL decides who may publish there); empty: the gateway does not subscribe to it."
        ),
    )
    coordinate_topic: str = "iot/coordinates/#"
    robot_chunk_topic: str = Field(
        "iot/chunks/create/+",
        description=(
            "Per-robot chunk topic filter: a robot publishes the 2019 chunk payload on "
            "iot/chunks/create/<robotId>, the broker's ACL ties that level to its username and the "
            "gateway checks the payload's robotId against it; empty: not subscribed."
        ),
    )

    # VDA 5050 vehicles
    vda5050_interface: str = Field(
        "uagv",
        pattern=r"^[^/#+]*$",
        description=(
            "Interface name, the first level of VDA 5050 topics "
            "(<interface>/<major>/<manufacturer>/<serialNumber>/<subtopic>); the gateway "
            "subscribes to <interface>/+/+/+/<state|visualization|connection|factsheet>; "
            "empty: VDA 5050 vehicles are not taken."
        ),
    )
    vda5050_map_transforms: dict[str, tuple[float, float, float]] = Field(
        default_factory=dict,
        description=(
            "Per VDA 5050 mapId, [dx, dy, rotation] (metres, metres, radians) taking a "
            "vehicle's map frame into the map's, as JSON, e.g. {\"hall1\": [10, 0, 0]}. "
            "Empty: every mapId is the map's frame; otherwise a vehicle on an unlisted mapId "
            "is stored and flagged, not drawn."
        ),
    )

    # Validation
    chunk_width: int = Field(100, ge=1, le=4096, description="Used until a map meta is set.")
    chunk_height: int = Field(100, ge=1, le=4096)
    max_grid: int = Field(1000, ge=1, description="Row/column bound until a map meta is set.")
    max_message_bytes: int = Field(256 * 1024, ge=1024)
    max_future_skew_s: float = Field(300.0, ge=0)
    ingest_new_robots_limit: str = Field(
        "10000/minute",
        description=(
            "Distinct robot ids the gateway has not seen before that it admits, in the `limits` "
            "notation (`;` between limits); beyond it a message of a new robot is dead-lettered "
            "`too_many_new_robots` (robots already seen pass). Bounds a flood of made-up ids "
            "where the broker does not authenticate robots. Empty: no limit."
        ),
    )
    # At most 24: receive-minus-event lag is stored in Int32 milliseconds.
    retention_days: int = Field(
        7,
        ge=1,
        le=24,
        description=(
            "History kept, in days of the service's clock; the processors' retention step drops "
            "older days and carries the floor forward."
        ),
    )
    # The service's clock (mapservice/adapters/clock.py): the wall clock by default; a
    # start instant and a rate run it simulated (tests drive weeks of history in minutes
    # through the same code production runs).
    clock_start: str = Field(
        "",
        description=(
            "Simulated clock: the instant (ISO 8601 UTC or epoch ms) the service's clock reads at "
            "MAPSERVICE_CLOCK_ORIGIN; empty: the wall clock."
        ),
    )
    clock_rate: float = Field(
        1.0,
        gt=0,
        le=1_000_000,
        description=(
            "Simulated clock: simulated seconds per real second (with MAPSERVICE_CLOCK_START)."
        ),
    )
    clock_origin: str = Field(
        "",
        description=(
            "Simulated clock: the real instant (ISO 8601 UTC or epoch ms) at which it reads "
            "MAPSERVICE_CLOCK_START; set the same on every process of a stack so their clocks "
            "agree; empty: when the process starts."
        ),
    )

    # Processors
    # Large enough that a backlog (after a slow insert) is caught up in one or two inserts:
    # each insert and its views cost a fixed ~30 ms, and 2,000 made 5,000 robots lag.
    sink_batch_size: int = Field(10000, ge=1)
    sink_batch_seconds: float = Field(
        0.2, gt=0, description="Longest wait to fill a history batch."
    )
    # A short window costs each insert's fixed cost more often; it is taken only while
    # stores are quick, i.e. while there is CPU to spare (processors/batch_window.py).
    sink_batch_min_seconds: float = Field(
        0.1,
        gt=0,
        description=(
            "Shortest wait to fill a history batch, taken while batches are stored quickly; the "
            "wait grows toward sink_batch_seconds as storing slows down."
        ),
    )
    # Feeding the pose views costs a fixed ~30 ms per insert: paid once a second, not per
    # batch (processors/history_consumer.py).
    sink_views_seconds: float = Field(
        1.0,
        gt=0,
        description=(
            "Longest the derived pose views (downsampled replay, timeline), the conflicts and the "
            "offset commits lag behind the stored history: the views are fed and the conflicts "
            "written once per this interval (at once when idle)."
        ),
    )

    snapshot_every_s: float = Field(600.0, ge=1, description="Snapshot interval of map and robots.")
    snapshot_grace_s: float = Field(
        60.0, ge=0, description="Snapshot S is built once now > S + grace."
    )

    # Live views, advertisements, conflicts, clock skew (the 2019 document's ideas I.3, I.4)
    advertisement_topic: str = Field(
        "iot/chunks/advertisement", description="2019 NEW_CHUNK_ADVERTISEMENT_TOPIC."
    )
    zone_advertisement_topic: str = Field(
        "iot/zones/advertisement",
        description=(
            "MQTT topic where robots learn that the zones changed (next to the chunk "
            "advertisements): the change, and where to GET the keep-out and speed masks."
        ),
    )
    robot_topic_root: str = Field(
        "iot/robots/",
        description=(
            "Root of each robot's own topics: the gateway delivers its commands on "
            "<root><robotId>/commands and reads its acks and outcomes from "
            "<root><robotId>/command-events (the broker's ACL lets only that robot use them)."
        ),
    )
    command_delivery_ttl_s: float = Field(
        30.0,
        gt=0,
        description=(
            "A command older than this when the gateway reads it (after an outage, a restart) "
            "is not delivered: a pause meant for minutes ago must not stop a robot now."
        ),
    )
    public_base_url: str = Field(
        "http://127.0.0.1:8080", description="Base of the chunkUrl in advertisements."
    )
    conflict_window_s: float = Field(
        60.0, ge=0, description="Different writes closer than this conflict."
    )
    clock_skew_threshold_s: float = Field(
        5.0, ge=0, description="|receive - event time| beyond this is flagged."
    )
    robot_offline_after_s: float = Field(
        10.0, gt=0, description="Silence after which a robot is offline."
    )

    # API
    api_host: str = "127.0.0.1"
    api_port: int = 8080
    ui_dir: Path | None = Field(
        None, description="Built replay UI to serve; empty: replay-ui/dist of the checkout."
    )
    admin_token: SecretStr = Field(
        SecretStr(""),
        description=(
            "Administrator credential (Authorization: Bearer ...): deletes, changing the map's "
            "geometry, everything else. Empty: generated on first start in local mode "
            "(DATA_DIR/secrets/admin-token); required (>= 32 characters) in production mode."
        ),
    )
    api_read_access: Literal["open", "token"] = Field(
        "open",
        description=(
            "`open`: reads need no credential (2019 robots read anonymously); `token`: every "
            "read needs a reader, writer or admin token."
        ),
    )
    api_reader_tokens: SecretStr = Field(
        SecretStr(""),
        description=(
            "Viewer credentials, comma-separated: read only. Empty: generated in local mode when "
            "api_read_access is `token` (DATA_DIR/secrets/reader-token)."
        ),
    )
    api_writer_tokens: SecretStr = Field(
        SecretStr(""),
        description=(
            "Robot/writer credentials, comma-separated (one per robot or integration): the 2019 "
            "REST writes (POST/PUT meta, POST chunks) and every read. Empty: generated in local "
            "mode (DATA_DIR/secrets/writer-token); in production, no REST writes but the admin's."
        ),
    )
    api_operator_tokens: SecretStr = Field(
        SecretStr(""),
        description=(
            "Operator credentials, comma-separated: every read, editing the annotations "
            "(points of interest, zones) and commanding robots. Empty: generated in local mode "
            "(DATA_DIR/secrets/operator-token)."
        ),
    )
    api_robot_tokens: SecretStr = Field(
        SecretStr(""),
        description=(
            "Robots' own REST credentials, `robotId=token` pairs, comma-separated: a writer "
            "token bound to one robot, which may POST chunks only under its own robotId (403 "
            "otherwise), as its MQTT user may publish only on its own topics."
        ),
    )
    api_metrics_access: Literal["open", "token", "off"] | None = Field(
        None,
        description=(
            "/metrics: `open`, `token` (the metrics or the admin token) or `off` (404). Empty: "
            "open in local mode, token in production mode."
        ),
    )
    api_metrics_token: SecretStr = Field(
        SecretStr(""),
        description=(
            "The scraper's credential for /metrics (Prometheus `authorization`); it opens nothing else."
        ),
    )
    api_docs_access: Literal["open", "token", "off"] | None = Field(
        None,
        description=(
            "/docs, /redoc and /openapi.json: `open`, `token` (any valid token) or `off` (404). "
            "Empty: open in local mode, token in production mode."
        ),
    )
    api_rate_limit: str = Field(
        "200/second;6000/minute",
        description=(
            "Requests per credential (or per client address when anonymous) in the `limits` "
            "notation, several separated by `;`; over it 429 with Retry-After. Empty: no limit. "
            "Probes (/healthz, /readyz) are not counted."
        ),
    )
    api_max_live_clients: int = Field(
        500,
        ge=0,
        description=(
            "WebSocket clients of /api/v1/live per API process; one more is closed with 1013 "
            "(try again later) and a reason naming this setting."
        ),
    )
    api_live_compression: bool = Field(
        False,
        description=(
            "Offer permessage-deflate on /api/v1/live. Off: compressing each message cost the "
            "API ~5 µs of CPU per event and viewer at 6,000 events/s (BENCHMARKS.md); a live "
            "message is ~300 bytes."
        ),
    )
    api_header_timeout_s: float = Field(
        10.0,
        gt=0,
        description=(
            "A connection must send a request's line and headers within this long (from "
            "connecting, or from the previous response), else it is closed (slowloris)."
        ),
    )
    api_idle_timeout_s: int = Field(
        5,
        ge=1,
        description=(
            "An idle keep-alive connection is closed after this long (uvicorn timeout_keep_alive)."
        ),
    )
    api_body_timeout_s: float = Field(
        30.0,
        gt=0,
        description=(
            "A request body must arrive within this long once its headers did (408 otherwise)."
        ),
    )
    api_max_body_bytes: int = Field(
        1024 * 1024,
        ge=1024,
        description=(
            "Largest request body the API reads (413 beyond); /clickhouse has its own limits."
        ),
    )
    api_allowed_origins: list[str] = Field(
        default_factory=list,
        description=(
            "Origins (https://host:port) besides the API's own host whose pages may open "
            "/api/v1/live; e.g. a dashboard served elsewhere."
        ),
    )
    api_allowed_hosts: list[str] = Field(
        default_factory=list,
        description=(
            "Host names (the Host header, without port) besides 127.0.0.1, localhost, ::1, the "
            "host of public_base_url and of api_allowed_origins under which /api/v1/live may be "
            "opened (a page of another site whose name resolves to this address: DNS rebinding)."
        ),
    )
    processors_status_url: str = Field(
        "",
        description=(
            "An API running apart from the processors: their health endpoint "
            "(http://host:port), whose /history-status gives /readyz's history_store and "
            "/api/v1/status (the replay UI's banner); empty: the API does not report whether "
            "the history is stored (`mapservice up` sets it)."
        ),
    )
    api_read_workers: int = Field(
        2,
        ge=1,
        description=(
            "Reads (/api/...) served at once per API process; more wait in a queue. Few: embedded "
            "ClickHouse runs one read at a time anyway, and each read's Python work competes "
            "with the processors for the interpreter (BENCHMARKS.md, the hostile-read test)."
        ),
    )
    api_read_queue: int = Field(
        32,
        ge=0,
        description=(
            "Reads waiting for one of api_read_workers; one more is 503 with Retry-After."
        ),
    )
    api_export_workers: int = Field(
        1,
        ge=1,
        description=(
            "Exports (/api/v1/exports/...) produced at once per API process, each in a thread "
            "of the exports' own pool; more wait in a queue."
        ),
    )
    api_export_queue: int = Field(
        4,
        ge=0,
        description=(
            "Exports waiting for one of api_export_workers; one more is 503 with Retry-After."
        ),
    )
    api_queue_wait_s: float = Field(
        10.0,
        gt=0,
        description=(
            "Longest a request waits in a queue (reads, exports) before it is answered "
            "503 with Retry-After."
        ),
    )
    api_caller_concurrency: int = Field(
        8,
        ge=1,
        description=(
            "Reads, exports and analysts' queries one credential (or one client address when "
            "anonymous) may have running or queued at once; one more is 429. At least a "
            "browser's 6 connections per host, so one replay UI page is never refused."
        ),
    )
    api_export_deadline_s: float = Field(
        300.0,
        gt=0,
        description=(
            "An export must be sent whole within this long; then it is aborted (the connection "
            "closed): a client that stops reading holds a worker and a buffer at most this long."
        ),
    )
    api_live_clients_per_caller: int = Field(
        20,
        ge=1,
        description=(
            "/api/v1/live connections per credential (or client address when anonymous); one "
            "more is refused with 429."
        ),
    )
    api_live_send_timeout_s: float = Field(
        10.0,
        gt=0,
        description=(
            "A live client whose connection takes no message for this long (it does not read) is "
            "closed with 1008 and a reason."
        ),
    )

    @field_validator("vda5050_map_transforms", mode="before")
    @classmethod
    def _transforms_as_json(cls, value: object) -> object:
        # The environment's JSON is decoded by pydantic-settings; the same text given as a
        # keyword (a stack's extra_env, a CLI option) is decoded here.
        return json.loads(value or "{}") if isinstance(value, str) else value

    @model_validator(mode="after")
    def _check_tls_and_topics(self) -> Settings:
        for hop, cert, key in (
            ("MQTT", self.mqtt_cert_file, self.mqtt_key_file),
            ("KAFKA_SSL", self.kafka_ssl_cert_file, self.kafka_ssl_key_file),
            ("CLICKHOUSE", self.clickhouse_cert_file, self.clickhouse_key_file),
        ):
            if (cert is None) != (key is None):
                raise ValueError(
                    f"MAPSERVICE_{hop}_CERT_FILE and MAPSERVICE_{hop}_KEY_FILE go "
                    "together (a client certificate needs its key)"
                )
        if (self.mqtt_ca_file or self.mqtt_cert_file) and not self.mqtt_url.startswith(
            ("mqtts:", "ssl:")
        ):
            raise ValueError(
                "MAPSERVICE_MQTT_CA_FILE/CERT_FILE are for TLS: use an mqtts:// "
                f"MAPSERVICE_MQTT_URL (not {self.mqtt_url})"
            )
        if (
            self.clickhouse_ca_file or self.clickhouse_cert_file
        ) and not self.resolved_clickhouse_dsn.startswith("https:"):
            raise ValueError(
                "MAPSERVICE_CLICKHOUSE_CA_FILE/CERT_FILE are for TLS: use an "
                "https:// MAPSERVICE_CLICKHOUSE_DSN"
            )
        if (
            self.kafka_ssl_ca_file or self.kafka_ssl_cert_file
        ) and "SSL" not in self.kafka_security_protocol.upper():
            raise ValueError(
                "MAPSERVICE_KAFKA_SSL_* files are for TLS: set "
                "MAPSERVICE_KAFKA_SECURITY_PROTOCOL to SSL or SASL_SSL"
            )
        if self.robot_chunk_topic and not self.robot_chunk_topic.endswith("/+"):
            raise ValueError(
                "MAPSERVICE_ROBOT_CHUNK_TOPIC must end with /+ (its last level is "
                f"the robot id), not {self.robot_chunk_topic!r}"
            )
        return self

    @model_validator(mode="after")
    def _refuse_default_secrets(self) -> Settings:
        robot_tokens(self.api_robot_tokens)  # malformed pairs: refused in every mode
        if self.mode == "production":
            admin = self.admin_token.get_secret_value()
            if not admin or admin == DEFAULT_ADMIN_TOKEN:
                raise ValueError(
                    f"MAPSERVICE_ADMIN_TOKEN is {'empty' if not admin else 'the old local default'}; "
                    f"set a secret of at least {MIN_TOKEN_CHARS} characters (openssl rand -hex 32) "
                    "before running with MAPSERVICE_MODE=production"
                )
            for name in (
                "admin_token",
                "api_reader_tokens",
                "api_writer_tokens",
                "api_operator_tokens",
                "api_metrics_token",
                "api_robot_tokens",
            ):
                tokens = (
                    list(robot_tokens(self.api_robot_tokens))
                    if name == "api_robot_tokens"
                    else token_list(getattr(self, name))
                )
                short = [t for t in tokens if len(t) < MIN_TOKEN_CHARS]
                if short:
                    raise ValueError(
                        f"MAPSERVICE_{name.upper()} holds a token of {len(short[0])} characters; "
                        f"production mode needs at least {MIN_TOKEN_CHARS} (openssl rand -hex 32)"
                    )
            if self.resolved_clickhouse_dsn.startswith("http") and (
                self.clickhouse_password.get_secret_value() == DEFAULT_CLICKHOUSE_PASSWORD
            ):
                raise ValueError(
                    "MAPSERVICE_CLICKHOUSE_PASSWORD is empty; set it before running "
                    "with MAPSERVICE_MODE=production"
                )
        return self

    @property
    def metrics_access(self) -> str:
        return self.api_metrics_access or ("open" if self.mode == "local" else "token")

    @property
    def docs_access(self) -> str:
        return self.api_docs_access or ("open" if self.mode == "local" else "token")

    @property
    def resolved_clickhouse_dsn(self) -> str:
        if self.clickhouse_dsn:
            return self.clickhouse_dsn
        return f"chdb://{(self.data_dir / 'clickhouse').resolve()}"

    @property
    def migrates_on_start(self) -> bool:
        return self.migrate_on_start if self.migrate_on_start is not None else self.mode == "local"

    @property
    def retention_ms(self) -> int:
        return self.retention_days * 86_400_000

    @cached_property
    def mqtt_subscriptions(self) -> list[str]:
        prefix = f"$share/{self.mqtt_share_group}/" if self.mqtt_share_group else ""
        # Only what vehicles publish: a master control's `order` and `instantActions` go
        # to the vehicles through the same subtree and are none of the gateway's business.
        vda = [
            f"{self.vda5050_interface}/+/+/+/{subtopic}"
            for subtopic in VDA5050_SUBTOPICS
            if self.vda5050_interface
        ]
        return [
            prefix + topic
            for topic in (
                self.create_chunk_topic,
                self.coordinate_topic,
                self.robot_chunk_topic,
                *vda,
                self.command_response_filter,
            )
            if topic
        ]

    @property
    def command_response_filter(self) -> str:
        """The MQTT filter of every robot's acks and outcomes: <root>+/command-events."""
        return (
            f"{self.robot_topic_root.rstrip('/')}/+/command-events" if self.robot_topic_root else ""
        )

    def command_topic(self, robot_id: str) -> str:
        """Where one robot reads its commands."""
        return f"{self.robot_topic_root.rstrip('/')}/{robot_id}/commands"

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

    def clickhouse_tls(self) -> dict[str, str]:
        """clickhouse-connect's TLS arguments (`get_client(**...)`) for an https:// DSN."""
        conf: dict[str, str] = {}
        if self.clickhouse_ca_file:
            conf["ca_cert"] = str(self.clickhouse_ca_file)
        if self.clickhouse_cert_file and self.clickhouse_key_file:
            conf["client_cert"] = str(self.clickhouse_cert_file)
            conf["client_cert_key"] = str(self.clickhouse_key_file)
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
