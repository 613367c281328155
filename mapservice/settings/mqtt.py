"""MQTT: the broker the gateway reads, its topics (2019's and VDA 5050's) and EMQX's admin API."""

from __future__ import annotations

import json
from pathlib import Path

from pydantic import BaseModel, Field, SecretStr, field_validator

# The subtopics a VDA 5050 vehicle publishes (master control publishes order and instantActions).
VDA5050_SUBTOPICS = ("state", "visualization", "connection", "factsheet")


class MqttSettings(BaseModel):
    """The broker and the topics the gateway subscribes to."""

    # Topic names as in the 2019 configuration, appendix A.3
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

    @field_validator("vda5050_map_transforms", mode="before")
    @classmethod
    def _transforms_as_json(cls, value: object) -> object:
        # The environment's JSON is decoded by pydantic-settings; the same text given as a
        # keyword (a stack's extra_env, a CLI option) is decoded here.
        return json.loads(value or "{}") if isinstance(value, str) else value
