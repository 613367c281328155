"""API access (api/access.py): every operation of the OpenAPI document asked with every kind
of credential, in both read modes; the docs, /metrics, the live WebSocket, CORS, JSON-only
writes and rate limits."""

from __future__ import annotations

import re

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from mapservice.api.access import READ, check_routes
from mapservice.api.app import create_app
from mapservice.api.credentials import Scope
from mapservice.api.live_hub import LiveHub
from starlette.websockets import WebSocketDisconnect

from mapservice.adapters.clock import ManualClock
from mapservice.settings import Settings
from mapservice.testing.memory_publisher import MemoryPublisher
from mapservice.testing.memory_store import MemoryStore

# The live stream answers only the service's own host names; the test client's default
# Host, "testserver", is not one.
LIVE_URL = "ws://localhost/api/v1/live"

NOW = 1_795_255_200_000  # 2026-11-21T10:00:00Z
ADMIN_TOKEN = "admin-" + "a" * 32
WRITER_TOKENS = ("robot-7-" + "w" * 32, "robot-8-" + "v" * 32)
READER_TOKEN = "viewer-" + "r" * 32
METRICS_TOKEN = "scraper-" + "m" * 32
OPERATOR_TOKEN = "operator-" + "p" * 32
# Bound to the robot of the 2019 spec's examples, which the generated requests write as.
ROBOT_TOKENS = {"lkjlkj": "own-robot-" + "o" * 32, "agv-7": "agv-seven-" + "s" * 32}

CREDENTIALS = {
    "none": None,
    "wrong": "not-a-token-of-this-service-" + "x" * 16,
    "reader": READER_TOKEN,
    "writer": WRITER_TOKENS[1],
    "admin": ADMIN_TOKEN,
    "metrics": METRICS_TOKEN,
    "robot": ROBOT_TOKENS["lkjlkj"],
    "operator": OPERATOR_TOKEN,
}

# The scope every operation must declare. A new operation fails test_every_operation_*
# until it is added here (and its scope declared in the API).
SCOPES = {
    "getLiveness": "public",
    "getReadiness": "public",
    "getMapAt": "read",
    "getMapPngAt": "read",
    "getRobotsAt": "read",
    "getRobotTrack": "read",
    "listPoses": "read",
    "listChunkEvents": "read",
    "getChunkContent": "read",
    "getChunkContentsBatch": "read",  # a read that POSTs its list of hashes
    "listEvents": "read",
    "getTimeline": "read",
    "listConflicts": "read",
    "exportTable": "read",
    "exportReplayMcap": "read",
    "getHistoryStats": "read",
    "getClientConfig": "read",
    "getServiceStatus": "read",
    "listChanges": "read",
    "getVdaVehicle": "read",
    "getVdaFleet": "read",
    "getLegacyMeta": "read",
    "listLegacyChunks": "read",
    "getLegacyChunk": "read",
    "getLegacyChunkPng": "read",
    "listLegacyRobots": "read",
    "postLegacyMeta": "write",
    "putLegacyMeta": "write",
    "postLegacyChunk": "write",
    "deleteLegacyMeta": "admin",
    "deleteLegacyChunks": "admin",
    "listAnnotations": "read",
    "listAnnotationEdits": "read",
    "getCostmapFilterMask": "read",
    "getCostmapFilterMaskYaml": "read",
    "getCostmapFilterInfo": "read",
    "createAnnotation": "operator",
    "changeAnnotation": "operator",
    "removeAnnotation": "operator",
    "importKeepOutMask": "operator",
    "listZoneViolations": "read",
    "sendCommand": "operator",
    "listCommands": "read",
    "getCallerAccess": "read",
}

# What each credential gets per scope: a status, or "ok" (anything the operation answers
# its input with: 2xx, 4xx but 401/403, never 500).
EXPECTED = {
    "open": {
        "public": dict.fromkeys(CREDENTIALS, "ok"),
        # Open reads ignore a stale token (a browser's after a rotation); writes do not.
        "read": dict.fromkeys(CREDENTIALS, "ok"),
        "write": {
            "none": 401,
            "wrong": 401,
            "reader": 403,
            "writer": "ok",
            "admin": "ok",
            "metrics": 403,
            "robot": "ok",
            "operator": 403,
        },
        "admin": {
            "none": 401,
            "wrong": 401,
            "reader": 403,
            "writer": 403,
            "admin": "ok",
            "metrics": 403,
            "robot": 403,
            "operator": 403,
        },
        # Shaping the floor: operators and the admin; readers, robots and writers may not.
        "operator": {
            "none": 401,
            "wrong": 401,
            "reader": 403,
            "writer": 403,
            "admin": "ok",
            "metrics": 403,
            "robot": 403,
            "operator": "ok",
        },
    },
    "token": {
        "public": dict.fromkeys(CREDENTIALS, "ok"),
        "read": {
            "none": 401,
            "wrong": 401,
            "reader": "ok",
            "writer": "ok",
            "admin": "ok",
            "metrics": 403,
            "robot": "ok",
            "operator": "ok",
        },
        "write": {
            "none": 401,
            "wrong": 401,
            "reader": 403,
            "writer": "ok",
            "admin": "ok",
            "metrics": 403,
            "robot": "ok",
            "operator": 403,
        },
        "admin": {
            "none": 401,
            "wrong": 401,
            "reader": 403,
            "writer": 403,
            "admin": "ok",
            "metrics": 403,
            "robot": 403,
            "operator": 403,
        },
        "operator": {
            "none": 401,
            "wrong": 401,
            "reader": 403,
            "writer": 403,
            "admin": "ok",
            "metrics": 403,
            "robot": 403,
            "operator": "ok",
        },
    },
}


def settings_for(read_access: str, **overrides) -> Settings:
    return Settings(
        admin_token=ADMIN_TOKEN,
        api_writer_tokens=",".join(WRITER_TOKENS),
        api_robot_tokens=",".join(f"{r}={t}" for r, t in ROBOT_TOKENS.items()),
        api_reader_tokens=READER_TOKEN,
        api_metrics_token=METRICS_TOKEN,
        api_operator_tokens=OPERATOR_TOKEN,
        api_read_access=read_access,
        api_rate_limit="",
        **overrides,
    )


def app_for(settings: Settings, **kwargs) -> FastAPI:
    return create_app(
        settings, MemoryStore(), {}, ManualClock(NOW), publisher=MemoryPublisher(), **kwargs
    )


def auth(credential: str) -> dict[str, str]:
    token = CREDENTIALS[credential]
    return {"Authorization": f"Bearer {token}"} if token else {}


def operations() -> list[tuple[str, str, dict]]:
    """(method, path, operation) of every operation the app's OpenAPI document lists."""
    doc = app_for(settings_for("open")).openapi()
    return [
        (method.upper(), path, op)
        for path, ops in doc["paths"].items()
        for method, op in ops.items()
    ]


def example_request(method: str, path: str, op: dict) -> dict:
    """Arguments for TestClient.request: path parameters filled in, required query
    parameters given plausible values, a JSON body where the operation takes one."""
    fill = {
        "content_hash": "00" * 16,
        "dataset": "robot-poses",
        "robot_id": "r1",
        "chunk_id": "row:0_column:0_2026-11-21T09:00:00",
    }
    url = re.sub(r"\{(\w+)\}", lambda m: fill.get(m.group(1), "x"), path)
    params = {}
    for p in op.get("parameters", []):
        if p["in"] == "query" and p.get("required"):
            params[p["name"]] = {"from": "2026-11-21T09:00:00Z", "to": "2026-11-21T09:30:00Z"}.get(
                p["name"], "1"
            )
    kwargs: dict = {"method": method, "url": url, "params": params}
    if "requestBody" in op or method in ("POST", "PUT"):
        kwargs["json"] = {"hashes": ["00" * 16]} if path.endswith("/batch") else {}
    return kwargs


OPERATIONS = operations()


def test_every_operation_declares_the_expected_scope() -> None:
    """Each operation of the OpenAPI document has a scope (x-mapservice-scope), the one this test expects, and security to match."""
    found = {op["operationId"]: op.get("x-mapservice-scope") for _, _, op in OPERATIONS}
    assert found == SCOPES, (
        "an operation's scope changed, or one is new: declare it (api/access.py) and list it here"
    )
    for method, _, op in OPERATIONS:
        scope = op["x-mapservice-scope"]
        expected = {"public": [], "read": [{}, {"bearer": []}]}.get(scope, [{"bearer": []}])
        assert op["security"] == expected, op["operationId"]
        # The refusals are documented (a client generator, schemathesis' status check).
        documented = set(op["responses"])
        assert ({"401", "403"} <= documented) == (scope in ("write", "admin", "operator")), op[
            "operationId"
        ]
        assert ("429" in documented) == (scope != "public"), op["operationId"]
        assert ("415" in documented) == (method in ("POST", "PUT")), op["operationId"]


@pytest.mark.parametrize("read_access", ["open", "token"])
@pytest.mark.parametrize("credential", list(CREDENTIALS))
@pytest.mark.parametrize(
    "method, path, op", OPERATIONS, ids=[op["operationId"] for _, _, op in OPERATIONS]
)
def test_every_operation_with_every_credential(read_access, credential, method, path, op) -> None:
    """The table: 401 without or with a wrong token, 403 with a token lacking the scope, else whatever the input earns (never 401, 403 or 500)."""
    client = TestClient(app_for(settings_for(read_access)), raise_server_exceptions=False)
    expected = EXPECTED[read_access][SCOPES[op["operationId"]]][credential]
    r = client.request(**example_request(method, path, op), headers=auth(credential))
    if expected == "ok":
        assert r.status_code not in (401, 403, 500), (r.status_code, r.text[:300])
    else:
        assert r.status_code == expected, (r.status_code, r.text[:300])
        assert r.headers["www-authenticate"].startswith("Bearer")
        if expected == 403:
            assert "insufficient_scope" in r.headers["www-authenticate"]


def test_token_read_mode_documents_reads_as_needing_a_token() -> None:
    """With MAPSERVICE_API_READ_ACCESS=token the OpenAPI document no longer offers reads without a credential."""
    doc = app_for(settings_for("token")).openapi()
    assert doc["paths"]["/api/v1/map"]["get"]["security"] == [{"bearer": []}]
    assert doc["components"]["securitySchemes"]["bearer"]["scheme"] == "bearer"


def test_an_app_with_a_route_without_scope_is_refused() -> None:
    """check_routes refuses a route that declares no scope (a new endpoint is never open by omission), and accepts one that does."""
    app = FastAPI()

    @app.get("/forgotten")
    def forgotten() -> dict:
        return {}

    with pytest.raises(RuntimeError, match="/forgotten"):
        check_routes(app)
    declared = FastAPI()
    declared.get("/declared", dependencies=[pytest.importorskip("fastapi").Depends(READ)])(
        forgotten
    )
    check_routes(declared)


def test_the_writer_may_post_chunks_as_a_2019_robot(wire) -> None:
    """A 2019 chunk POST with a writer token in the header is stored (published), without one refused: the header is the only change."""
    publisher = MemoryPublisher()
    store = MemoryStore()
    app = create_app(settings_for("open"), store, {}, ManualClock(wire.now_ms), publisher=publisher)
    client = TestClient(app)
    doc = wire.chunk_doc()
    assert client.post("/api/chunk-service/chunks", json=doc).status_code == 401
    r = client.post(
        "/api/chunk-service/chunks",
        json=doc,
        headers={"Authorization": f"Bearer {WRITER_TOKENS[0]}"},
    )
    assert r.status_code == 200, r.text
    publisher.poll()
    assert sum(len(v) for v in publisher.records.values()) == 1
    # Reads stay open for robots that read anonymously (MAPSERVICE_API_READ_ACCESS=open).
    assert client.get("/api/chunk-service/chunks").status_code == 200


def test_a_robot_token_writes_chunks_only_as_its_own_robot(wire) -> None:
    """A robot token POSTs its own robot's chunk (200) and is refused another robot's (403, naming both); a writer token may write as any."""
    publisher = MemoryPublisher()
    client = TestClient(
        create_app(
            settings_for("open"), MemoryStore(), {}, ManualClock(wire.now_ms), publisher=publisher
        )
    )
    own = client.post(
        "/api/chunk-service/chunks",
        json={**wire.chunk_doc(), "robotId": "agv-7"},
        headers={"Authorization": f"Bearer {ROBOT_TOKENS['agv-7']}"},
    )
    assert own.status_code == 200, own.text
    other = client.post(
        "/api/chunk-service/chunks",
        json={**wire.chunk_doc(), "robotId": "agv-8"},
        headers={"Authorization": f"Bearer {ROBOT_TOKENS['agv-7']}"},
    )
    assert (
        other.status_code == 403
        and "agv-7" in other.json()["detail"]
        and "agv-8" in other.json()["detail"]
    )
    anyone = client.post(
        "/api/chunk-service/chunks",
        json={**wire.chunk_doc(), "robotId": "agv-8"},
        headers={"Authorization": f"Bearer {WRITER_TOKENS[0]}"},
    )
    assert anyone.status_code == 200
    publisher.poll()
    assert (
        sum(len(v) for v in publisher.records.values()) == 2
    )  # the refused one never reached Kafka


def test_robot_tokens_must_be_pairs_and_long_in_production() -> None:
    """A token without its robotId is refused at start; production refuses a short robot token."""
    with pytest.raises(ValueError, match="robotId=token"):
        Settings(api_robot_tokens="just-a-token")
    with pytest.raises(ValueError, match="API_ROBOT_TOKENS"):
        Settings(
            mode="production",
            admin_token=ADMIN_TOKEN,
            clickhouse_dsn="chdb:///x",
            api_robot_tokens="agv-7=short",
        )


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
