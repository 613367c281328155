"""GET /api/v1/client-config: what the /controller page needs to publish like a robot."""

from __future__ import annotations

from fastapi.testclient import TestClient

from mapservice.api.app import create_app
from mapservice.api.routers.client_config import coordinate_prefix
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore


def _get(settings: Settings) -> dict:
    r = TestClient(create_app(settings, MemoryStore())).get("/api/v1/client-config")
    assert r.status_code == 200
    return r.json()


def test_hands_out_the_configured_websocket_url_and_topics() -> None:
    """The page gets MAPSERVICE_MQTT_WS_URL and the 2019 topics the gateway reads."""
    body = _get(Settings(mqtt_ws_url="ws://127.0.0.1:9001/mqtt"))
    assert body == {
        "mqtt_ws_url": "ws://127.0.0.1:9001/mqtt",
        "coordinate_topic_prefix": "iot/coordinates/",
        "create_chunk_topic": "iot/chunks/create",
        "robot_chunk_topic_prefix": "iot/chunks/create/",
    }


def test_no_per_robot_chunk_topic_is_null() -> None:
    """With the per-robot chunk topic turned off the page is told to use the 2019 topic."""
    assert _get(Settings(robot_chunk_topic=""))["robot_chunk_topic_prefix"] is None


def test_no_websocket_url_is_null(monkeypatch) -> None:
    """Without a configured WebSocket URL the page is told so (null), not given a guess."""
    monkeypatch.delenv("MAPSERVICE_MQTT_WS_URL", raising=False)
    assert _get(Settings())["mqtt_ws_url"] is None


def test_setting_reads_the_environment(monkeypatch) -> None:
    """MAPSERVICE_MQTT_WS_URL sets mqtt_ws_url."""
    monkeypatch.setenv("MAPSERVICE_MQTT_WS_URL", "wss://mqtt.example.com/mqtt")
    assert Settings().mqtt_ws_url == "wss://mqtt.example.com/mqtt"


def test_coordinate_prefix_follows_the_gateway_topic() -> None:
    """Pose topics are <prefix><robotId> for '#', '+' and a bare coordinate topic alike."""
    assert coordinate_prefix("iot/coordinates/#") == "iot/coordinates/"
    assert coordinate_prefix("plant7/coords/+") == "plant7/coords/"
    assert coordinate_prefix("iot/coordinates") == "iot/coordinates/"
