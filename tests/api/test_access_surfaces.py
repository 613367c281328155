"""API access beyond the operations' table: the docs, /metrics, the live WebSocket, CORS,
rate limits, and what a caller learns of its own role."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from mapservice.api.credentials import Scope
from mapservice.api.live_hub import LiveHub
from mapservice.settings import Settings
from tests.api.access_kit import CREDENTIALS, LIVE_URL, READER_TOKEN, app_for, auth, settings_for

# --- docs and metrics --------------------------------------------------------------------------

DOCS = ("/docs", "/redoc", "/openapi.json")


@pytest.mark.parametrize(
    "access, credential, expected",
    [
        ("open", "none", 200),
        ("off", "admin", 404),
        ("token", "none", 401),
        ("token", "wrong", 401),
        ("token", "metrics", 403),
        ("token", "reader", 200),
        ("token", "writer", 200),
        ("token", "admin", 200),
    ],
)
def test_docs_follow_their_setting(access, credential, expected) -> None:
    """/docs, /redoc and /openapi.json: open, off (404) or for any reader/writer/admin token."""
    client = TestClient(app_for(settings_for("open", api_docs_access=access)))
    for path in DOCS:
        assert client.get(path, headers=auth(credential)).status_code == expected, path


@pytest.mark.parametrize(
    "access, credential, expected",
    [
        ("open", "none", 200),
        ("off", "admin", 404),
        ("token", "none", 401),
        ("token", "wrong", 401),
        ("token", "reader", 403),
        ("token", "writer", 403),
        ("token", "metrics", 200),
        ("token", "admin", 200),
    ],
)
def test_metrics_follow_their_setting(access, credential, expected) -> None:
    """/metrics: open, off (404), or the metrics token (or the admin's) only."""
    client = TestClient(app_for(settings_for("open", api_metrics_access=access)))
    assert client.get("/metrics", headers=auth(credential)).status_code == expected


def test_production_defaults_guard_docs_and_metrics_and_keep_probes_open() -> None:
    """In production mode docs and metrics need a token by default; /healthz and /readyz stay open for the kubelet."""
    settings = settings_for("open", mode="production")
    assert (settings.docs_access, settings.metrics_access) == ("token", "token")
    client = TestClient(app_for(settings))
    assert client.get("/metrics").status_code == 401
    assert client.get("/openapi.json").status_code == 401
    assert client.get("/healthz").status_code == 200 and client.get("/readyz").status_code == 200
    local = Settings()
    assert (local.docs_access, local.metrics_access) == ("open", "open")


# --- the live WebSocket ------------------------------------------------------------------------


def test_live_stream_needs_a_token_where_reads_do() -> None:
    """With reads by token, /api/v1/live refuses a handshake without one (1008) and accepts a token in the header or as a subprotocol."""
    client = TestClient(app_for(settings_for("token"), live_hub=LiveHub()))
    with pytest.raises(WebSocketDisconnect) as refused:
        with client.websocket_connect(LIVE_URL) as ws:
            ws.receive_json()
    assert refused.value.code == 1008
    with client.websocket_connect(LIVE_URL, headers=auth("reader")) as ws:
        ws.close()
    with client.websocket_connect(
        LIVE_URL, subprotocols=["mapservice.live", f"bearer.{READER_TOKEN}"]
    ) as ws:
        assert ws.accepted_subprotocol == "mapservice.live"
        ws.close()
    # An empty `bearer.` is no token: refused with the reason that says what to send.
    with pytest.raises(WebSocketDisconnect) as refused:
        with client.websocket_connect(LIVE_URL, subprotocols=["mapservice.live", "bearer."]) as ws:
            ws.receive_json()
    assert refused.value.code == 1008 and "needs" in refused.value.reason
    open_client = TestClient(app_for(settings_for("open"), live_hub=LiveHub()))
    with open_client.websocket_connect(LIVE_URL) as ws:
        ws.close()


def test_live_clients_are_bounded() -> None:
    """One client more than MAPSERVICE_API_MAX_LIVE_CLIENTS is closed with 1013 and a reason naming the setting; a place frees when one leaves."""
    hub = LiveHub()
    client = TestClient(app_for(settings_for("open", api_max_live_clients=1), live_hub=hub))
    with client.websocket_connect(LIVE_URL) as first:
        for _ in range(200):
            if hub.subscribers:
                break
            client.portal.call(lambda: None)
        with client.websocket_connect(LIVE_URL) as second:
            closed = second.receive()
        assert closed["code"] == 1013 and "MAPSERVICE_API_MAX_LIVE_CLIENTS" in closed["reason"]
        first.close()
    for _ in range(200):
        if not hub.subscribers:
            break
        client.portal.call(lambda: None)
    with client.websocket_connect(LIVE_URL) as again:
        again.close()


# --- CORS, rate limits -------------------------------------------------------------------------


def test_cors_only_for_listed_origins() -> None:
    """A preflight from a listed origin is answered with its origin and the Authorization header; another origin, or none listed, gets no CORS grant."""
    client = TestClient(
        app_for(settings_for("open", api_allowed_origins=["https://dash.example.com"]))
    )
    preflight = {
        "Access-Control-Request-Method": "POST",
        "Access-Control-Request-Headers": "authorization,content-type",
    }
    r = client.options(
        "/api/chunk-service/chunks", headers={"Origin": "https://dash.example.com", **preflight}
    )
    assert r.status_code == 200
    assert r.headers["access-control-allow-origin"] == "https://dash.example.com"
    assert "authorization" in r.headers["access-control-allow-headers"].lower()
    r = client.options(
        "/api/chunk-service/chunks", headers={"Origin": "https://evil.example", **preflight}
    )
    assert "access-control-allow-origin" not in r.headers
    r = client.get("/api/v1/stats", headers={"Origin": "https://evil.example"})
    assert r.status_code == 200 and "access-control-allow-origin" not in r.headers
    default = TestClient(app_for(settings_for("open")))
    r = default.get("/api/v1/stats", headers={"Origin": "https://dash.example.com"})
    assert "access-control-allow-origin" not in r.headers


def test_rate_limit_per_credential_with_retry_after() -> None:
    """Over MAPSERVICE_API_RATE_LIMIT a caller gets 429 with Retry-After; another credential has its own budget; probes are never limited."""
    client = TestClient(
        app_for(settings_for("open").model_copy(update={"api_rate_limit": "3/minute"}))
    )
    for _ in range(3):
        assert client.get("/api/v1/stats", headers=auth("writer")).status_code == 200
    r = client.get("/api/v1/stats", headers=auth("writer"))
    assert r.status_code == 429 and 1 <= int(r.headers["retry-after"]) <= 60
    assert "MAPSERVICE_API_RATE_LIMIT" in r.json()["detail"]
    assert client.get("/api/v1/stats", headers=auth("reader")).status_code == 200
    # Anonymous callers and wrong tokens share their address's budget: guessing opens none.
    for _ in range(3):
        client.get("/api/v1/stats")
    assert client.get("/api/v1/stats", headers=auth("wrong")).status_code == 429
    assert all(client.get("/healthz").status_code == 200 for _ in range(10))


def test_the_default_rate_limit_is_parsed() -> None:
    """The default MAPSERVICE_API_RATE_LIMIT is valid `limits` notation and allows bursts of a replay UI."""
    from limits import parse_many

    items = parse_many(Settings().api_rate_limit)
    assert items and items[0].amount >= 100
    assert Scope.READ.value == "read"


@pytest.mark.parametrize(
    "credential, role, scopes",
    [
        ("operator", "operator", ["operator", "read"]),
        ("reader", "reader", ["read"]),
        ("writer", "writer", ["read", "write"]),
        ("none", None, []),
        ("wrong", None, []),  # reads are open: a stale token is no one, not a refusal
    ],
)
def test_the_caller_learns_its_role_and_scopes(credential, role, scopes) -> None:
    """GET /api/v1/caller names the token's role and scopes (the replay page offers editing
    only to the operator scope), never the token."""
    client = TestClient(app_for(settings_for("open")))
    r = client.get("/api/v1/caller", headers=auth(credential))
    assert r.status_code == 200, r.text
    assert r.json() == {"role": role, "scopes": scopes}
    assert CREDENTIALS[credential] is None or CREDENTIALS[credential] not in r.text
