"""Requests only under the service's own host names (api/limits.py HostCheck): a page of
another site whose name resolves to this address (DNS rebinding) reads nothing, whatever
the route and the read mode, the analysts' /clickhouse and the live WebSocket included;
the probes answer under any Host (the kubelet sends the pod's address), and IP addresses,
the loopback names and the configured names are the service's own."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.settings import Settings
from mapservice.testing.memory_publisher import MemoryPublisher
from mapservice.testing.memory_store import MemoryStore
from tests.api.access_kit import ADMIN_TOKEN, NOW, settings_for
from tests.api.test_access import OPERATIONS, example_request

FOREIGN = ["evil.example", "evil.example:8080", "127.0.0.1.nip.io", "localhost.evil.example"]
PROBES = {"getLiveness", "getReadiness"}
# Routes outside the OpenAPI document: the UI's pages, the docs, the scrape, no route.
UNDOCUMENTED = ["/", "/docs", "/openapi.json", "/metrics", "/no/such/route"]
ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}


def _client(read_access: str, **overrides) -> TestClient:
    from mapservice.sql.http_protocol import SqlUser, clickhouse_http_app

    sql_app = clickhouse_http_app(object(), [SqlUser("analyst", "s3cret", read_only=True)])  # type: ignore[arg-type]
    app = create_app(
        settings_for(read_access, **overrides),
        MemoryStore(),
        {},
        ManualClock(NOW),
        publisher=MemoryPublisher(),
        sql_app=sql_app,
    )
    return TestClient(app, raise_server_exceptions=False)


@pytest.fixture(scope="module", params=["open", "token"])
def client(request) -> TestClient:
    return _client(request.param)


@pytest.mark.parametrize("host", FOREIGN)
@pytest.mark.parametrize(
    "method, path, op", OPERATIONS, ids=[op["operationId"] for _, _, op in OPERATIONS]
)
def test_every_operation_under_a_foreign_host_is_refused(client, host, method, path, op) -> None:
    """With the admin's token, in both read modes: 421 naming the setting, except the
    probes, which answer as under any name."""
    r = client.request(**example_request(method, path, op), headers={**ADMIN, "host": host})
    if op["operationId"] in PROBES:
        assert r.status_code in (200, 503), r.text
        return
    assert r.status_code == 421, (r.status_code, r.text[:200])
    assert "MAPSERVICE_API_ALLOWED_HOSTS" in r.json()["detail"]


@pytest.mark.parametrize("host", FOREIGN)
@pytest.mark.parametrize("path", [*UNDOCUMENTED, "/clickhouse/ping", "/clickhouse/"])
def test_pages_docs_metrics_and_clickhouse_under_a_foreign_host_are_refused(
    client, host, path
) -> None:
    r = client.get(path, headers={**ADMIN, "host": host})
    assert r.status_code == 421, (r.status_code, r.text[:200])
    r = client.post(
        "/clickhouse/",
        content=b"SELECT 1",
        headers={"host": host, "X-ClickHouse-User": "analyst", "X-ClickHouse-Key": "s3cret"},
    )
    assert r.status_code == 421, r.text[:200]


@pytest.mark.parametrize(
    "host",
    [
        "localhost",
        "localhost:8000",
        "127.0.0.1:8080",
        "[::1]:8080",
        "10.1.2.3:8080",  # a pod's address: the kubelet, Prometheus, in-cluster clients
        "[fd00::7]",
        "maps.plant.example",  # MAPSERVICE_API_ALLOWED_HOSTS
        "MAPS.Plant.Example:443",
        "mapservice.example.com",  # MAPSERVICE_PUBLIC_BASE_URL's host
        "dashboard.example.org",  # an allowed origin's host
    ],
)
def test_the_service_s_own_names_and_addresses_are_answered(host) -> None:
    client = _client(
        "open",
        api_allowed_hosts=["maps.plant.example"],
        public_base_url="https://mapservice.example.com",
        api_allowed_origins=["https://dashboard.example.org"],
    )
    for path in ("/api/v1/robots", "/api/chunk-service/meta", "/clickhouse/ping", "/healthz"):
        assert client.get(path, headers={"host": host}).status_code != 421, (host, path)


def test_without_a_host_header_only_the_probes_answer() -> None:
    """HTTP/1.0 may send none: no name, no proof of being addressed to this service."""
    client = _client("open")
    for path, refused in (("/api/v1/robots", True), ("/healthz", False)):
        r = client.get(path, headers={"host": ""})
        assert (r.status_code == 421) == refused, (path, r.status_code)


@pytest.mark.parametrize("host", FOREIGN)
def test_the_live_websocket_under_a_foreign_host_is_closed_before_accept(host) -> None:
    client = TestClient(create_app(Settings(), MemoryStore()))
    with pytest.raises(WebSocketDisconnect) as refused:
        with client.websocket_connect(
            "ws://x/api/v1/live", headers={"host": host, "origin": f"http://{host}"}
        ) as ws:
            ws.receive_json()
    assert refused.value.code == 1008 and "MAPSERVICE_API_ALLOWED_HOSTS" in refused.value.reason
