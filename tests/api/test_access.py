"""API access (api/access.py): every operation of the OpenAPI document asked with every kind
of credential, in both read modes; which routes must declare a scope; writers' and robots'
tokens. The docs, /metrics, the live WebSocket, CORS and rate limits are in
test_access_surfaces.py."""

from __future__ import annotations

import functools
import re

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.access import READ, check_routes
from mapservice.api.app import create_app
from mapservice.settings import Settings
from mapservice.testing.memory_publisher import MemoryPublisher
from mapservice.testing.memory_store import MemoryStore
from tests.api.access_kit import (
    ADMIN_TOKEN,
    CREDENTIALS,
    ROBOT_TOKENS,
    WRITER_TOKENS,
    app_for,
    auth,
    settings_for,
)

# The scope every operation must declare. A new operation fails test_every_operation_*
# until it is added here (and its scope declared in the API).
SCOPES = {
    "getLiveness": "public",
    "getReadiness": "public",
    "getMapAt": "read",
    "getMapPngAt": "read",
    "getRobotsAt": "read",
    "getRobotTrack": "read",
    "getRobotTrackBuckets": "read",
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
    "listIncidents": "read",
    "getHeatmap": "read",
    "sendCommand": "operator",
    "listCommands": "read",
    "getCallerAccess": "read",
    # the incident alerts' webhooks: the plant's integration, an operator's business
    "registerWebhook": "operator",
    "listWebhooks": "operator",
    "showWebhookSecret": "operator",
    "removeWebhook": "operator",
    "resumeWebhook": "operator",
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


@functools.cache
def shared_app(read_access: str) -> FastAPI:
    """One app per read-access mode for the table's cases: building an app costs several
    times the request each case makes, over a thousand cases. Built on the first case's
    call, under the fast tests' environment (tests/conftest.py `_hermetic_env`); the
    cases assert only who may call what, which no earlier case's request changes."""
    return app_for(settings_for(read_access))


@pytest.mark.parametrize("read_access", ["open", "token"])
@pytest.mark.parametrize("credential", list(CREDENTIALS))
@pytest.mark.parametrize(
    "method, path, op", OPERATIONS, ids=[op["operationId"] for _, _, op in OPERATIONS]
)
def test_every_operation_with_every_credential(read_access, credential, method, path, op) -> None:
    """The table: 401 without or with a wrong token, 403 with a token lacking the scope, else whatever the input earns (never 401, 403 or 500)."""
    client = TestClient(shared_app(read_access), raise_server_exceptions=False)
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
