"""What a browser page needs to talk to the service like a robot: the broker's WebSocket URL
and the 2019 MQTT topics (the /controller page reads it at start)."""

from __future__ import annotations

from fastapi import APIRouter, Depends
from pydantic import BaseModel

from ..access import READ
from ..deps import SettingsDep

router = APIRouter(
    prefix="/api/v1/client-config", tags=["client-config"], dependencies=[Depends(READ)]
)


class ClientConfig(BaseModel):
    mqtt_ws_url: str | None  # None: no WebSocket listener configured (MAPSERVICE_MQTT_WS_URL)
    coordinate_topic_prefix: str  # a robot publishes its pose on <prefix><robotId>
    create_chunk_topic: str
    # A robot publishes its chunks on <prefix><robotId>, the topic a broker's ACL ties to
    # its username; None: the gateway does not read per-robot chunk topics.
    robot_chunk_topic_prefix: str | None


def coordinate_prefix(coordinate_topic: str) -> str:
    """'iot/coordinates/#' -> 'iot/coordinates/', as the gateway reads it (ingest/router.py)."""
    if coordinate_topic.endswith(("#", "+")):
        return coordinate_topic[:-1]
    return coordinate_topic.rstrip("/") + "/"


@router.get("", operation_id="getClientConfig", response_model=ClientConfig)
def get_client_config(settings: SettingsDep) -> ClientConfig:
    # The service's own broker credentials stay on the server: where the broker checks
    # robot identities, the page connects with a robot's credential its user types in.
    return ClientConfig(
        mqtt_ws_url=settings.mqtt_ws_url or None,
        coordinate_topic_prefix=coordinate_prefix(settings.coordinate_topic),
        create_chunk_topic=settings.create_chunk_topic,
        robot_chunk_topic_prefix=(
            coordinate_prefix(settings.robot_chunk_topic) if settings.robot_chunk_topic else None
        ),
    )
