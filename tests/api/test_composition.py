"""The API is composed in api/ (api/composition.py): the live hub fed by the relay from its
thread, the REST writes' publisher, the health checks of what runs beside it, and the uvicorn
server; nothing is read or served before `start`/`serve`."""

from __future__ import annotations

import asyncio
import threading

import pytest
from fastapi.testclient import TestClient

from mapservice.api.composition import Api, compose_api
from mapservice.api.context import context_of
from mapservice.core.live_messages import LiveText
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore


def _settings(tmp_path) -> Settings:
    """Production settings without an analyst password: no analysts' SQL, so no ClickHouse
    engine is opened (embedded chDB allows one data path per process)."""
    return Settings(
        mode="production",
        admin_token="t" * 32,
        clickhouse_dsn="http://127.0.0.1:1",
        clickhouse_password="p" * 16,
        kafka_bootstrap="127.0.0.1:1",
        data_dir=tmp_path,
        api_host="127.0.0.1",
        api_port=18_999,
    )


def _compose(settings: Settings, **health) -> Api:
    async def build() -> Api:
        return await compose_api(
            settings,
            MemoryStore(),
            **{"readiness": {}, "liveness": {}, "advisory": {}, "history_status": None, **health},
        )

    return asyncio.run(build())


def test_the_parts_are_wired_into_the_app_and_its_server(tmp_path) -> None:
    """The hub and publisher are the app's; the hub is ready once the relay reads the live
    topic; the server serves this app where the settings say."""
    api = _compose(_settings(tmp_path))
    context = context_of(api.app)
    assert context.live is api.hub and context.publisher is api.publisher
    assert api.hub.ready() is False
    api.relay.assigned.set()
    assert api.hub.ready() is True
    config = api.server.config
    assert config.app is api.app and (config.host, config.port) == ("127.0.0.1", 18_999)


def test_the_relay_feeds_the_hub_on_the_event_loop(tmp_path) -> None:
    """Messages the relay reads on its own thread reach a subscriber through the loop."""

    async def run() -> list:
        api = await compose_api(
            _settings(tmp_path),
            MemoryStore(),
            readiness={},
            liveness={},
            advisory={},
            history_status=None,
        )
        queue = api.hub.subscribe()
        message = LiveText('{"type": "pose", "robot_id": "r1"}')
        feeder = threading.Thread(target=api.relay.on_messages, args=([message],))
        feeder.start()
        feeder.join()
        return [await asyncio.wait_for(queue.get(), 5)]

    (got,) = asyncio.run(run())
    assert got["robot_id"] == "r1"


def test_the_health_of_what_runs_beside_it_is_what_the_api_reports(tmp_path) -> None:
    """/readyz requires `readiness` and reports `advisory`; /healthz answers `liveness`;
    /api/v1/status says what `history_status` says."""
    storing = {
        "storing": False,
        "failing_since_ms": 1,
        "last_stored_ms": None,
        "reason": "disk full",
    }
    api = _compose(
        _settings(tmp_path),
        readiness={"history_store": lambda: False},
        liveness={"history_consumer": lambda: True},
        advisory={"kafka": lambda: False},
        history_status=lambda: storing,
    )
    with TestClient(api.app) as client:
        ready = client.get("/readyz")
        assert ready.status_code == 503
        assert ready.json()["checks"] == {"history_store": False, "kafka": False}
        live = client.get("/healthz")
        assert live.status_code == 200 and live.json()["checks"] == {"history_consumer": True}
    assert context_of(api.app).history_status() is storing


def test_stopping_closes_the_rest_writes_producer(tmp_path) -> None:
    """A 2019 REST write made the publisher's producer; stopping the API closes it rather
    than leave it dialling Kafka until the process exits."""
    api = _compose(_settings(tmp_path))
    api.publisher.publish("t", b"k", b"v", lambda _error: None)
    assert api.publisher.connected
    asyncio.run(api.stop())
    assert not api.publisher.connected
    with pytest.raises(RuntimeError, match="closed"):
        api.publisher.publish("t", b"k", b"v", lambda _error: None)
