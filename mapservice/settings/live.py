"""What the service tells robots and viewers as it happens: advertisements, commands'
delivery, conflicts, clock skew and robots going offline (the 2019 document's ideas I.3, I.4)."""

from __future__ import annotations

from pydantic import BaseModel, Field, SecretStr, field_validator

from mapservice.core.areas import DEFAULT_AREA_CHUNKS
from mapservice.core.webhooks import parse_networks


class LiveSettings(BaseModel):
    """Advertisement and command topics, and the thresholds of conflicts, skew and offline."""

    advertisement_topic: str = Field(
        "iot/chunks/advertisement", description="2019 NEW_CHUNK_ADVERTISEMENT_TOPIC."
    )
    advertise_on_2019_topic: bool = Field(
        True,
        description=(
            "Advertise each chunk change on the 2019 topic too (every robot subscribed to it "
            "receives every change of the plant). Off only where no 2019 robot runs: robots "
            "of this project read the area topics."
        ),
    )
    advertisement_area_chunks: int = Field(
        DEFAULT_AREA_CHUNKS,
        ge=1,
        le=100_000,
        description=(
            "Side of an advertisement area in chunks: a change of chunk (row, column) is also "
            "advertised on <advertisement_topic>/area/<row // n>/<column // n>, which robots "
            "subscribe to around them. Robots must use the same value (--area-chunks)."
        ),
    )
    zone_advertisement_topic: str = Field(
        "iot/zones/advertisement",
        description=(
            "MQTT topic where robots learn that the zones changed (next to the chunk "
            "advertisements): the change, and where to GET the keep-out and speed masks."
        ),
    )
    incident_alert_topic_root: str = Field(
        "iot/incidents/",
        description=(
            "Root of the incident alerts' MQTT topics: every finding (new, changed, ended, "
            "retracted) on <root><kind>, QoS 1, the last of each kind retained. Only the "
            "processors may publish there; every user may subscribe."
        ),
    )
    webhook_signing_key: SecretStr = Field(
        SecretStr(""),
        description=(
            "Key every webhook's secret is derived from (hex HMAC-SHA256 of the webhook's id "
            "under it), so no secret is stored; the API and every processors replica need the "
            "same one, and changing it changes every webhook's secret. Empty: generated on first "
            "start in local mode (DATA_DIR/secrets/webhook-signing-key); in production, set it "
            "(at least 32 characters) to register and deliver to webhooks."
        ),
    )
    webhooks_max: int = Field(
        20, ge=0, le=1000, description="Webhooks that may be registered at once (409 beyond)."
    )
    webhook_registry_poll_s: float = Field(
        5.0,
        gt=0,
        description=(
            "How often each processors replica re-reads the registered webhooks (a new, removed "
            "or resumed one takes effect within this long) and reports its deliveries to them."
        ),
    )
    webhook_timeout_s: float = Field(
        5.0, gt=0, description="A webhook delivery's try fails without a 2xx answer within this."
    )
    webhook_max_tries: int = Field(
        6,
        ge=1,
        description=(
            "Tries of one delivery (waiting 1, 2, 4 ... s between them, up to "
            "webhook_backoff_cap_s) before its webhook is paused with the reason."
        ),
    )
    webhook_backoff_cap_s: float = Field(
        60.0, gt=0, description="Longest wait between two tries of a webhook delivery."
    )
    webhook_networks: str = Field(
        "",
        description=(
            "Networks besides the public Internet that webhooks may be sent to (CIDRs, comma "
            "separated, e.g. the plant's receivers' 10.20.0.0/16; 127.0.0.0/8 for a receiver on "
            "this machine). Checked on every address a delivery connects to, after DNS; "
            "loopback, link-local (cloud metadata), private and reserved addresses outside "
            "them are refused, and the service's own store, Kafka and MQTT endpoints always."
        ),
    )
    webhook_max_queued: int = Field(
        10_000,
        ge=1,
        description=(
            "Deliveries waiting in each processors replica, all webhooks together; past it "
            "the oldest is dropped and counted."
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
        10.0, gt=0, description="Silence after which a robot is offline (and an incident)."
    )
    incident_near_miss_m: float = Field(
        1.0, gt=0, description="Two robots closer than this, one of them moving: a near miss."
    )
    incident_moving_m_s: float = Field(
        0.05, ge=0, description="A robot faster than this is moving (for near misses)."
    )
    incident_stuck_m: float = Field(
        0.1,
        gt=0,
        description="A robot with a planned path that stayed this close to where it stands "
        "for incident_stuck_s is stuck.",
    )
    incident_stuck_s: float = Field(30.0, gt=0, description="See incident_stuck_m.")
    incident_battery_low_percent: float = Field(
        15.0, gt=0, le=100, description="A battery below this level, not charging, is low."
    )
    incident_command_ack_timeout_s: float = Field(
        10.0,
        gt=0,
        description="A command the robot has not acknowledged this long after it was "
        "issued is a command_failed incident (as is one it rejected).",
    )
    incident_memory_s: float = Field(
        300.0,
        ge=60,
        description="How much recent history the processors keep in memory to find "
        "incidents; poses older than this (late ones) are read from the store.",
    )
    incident_refresh_s: float = Field(
        10.0,
        ge=1,
        le=300,
        description="How often the stored row of an ongoing incident is brought up to "
        "its end (and announced on the live stream) while nothing else about it changes: "
        "a run that goes on costs a row this often, not one per stored batch. Begins, "
        "ends and other changes are written at once.",
    )

    @field_validator("webhook_networks")
    @classmethod
    def _networks(cls, value: str) -> str:
        parse_networks(value)  # refused at start, with what is wrong, not at a delivery
        return value
