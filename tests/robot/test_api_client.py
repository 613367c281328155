"""The robot side's REST client (robot/api_client.py): which token it sends, and that it
waits out a 429 instead of failing a map upload half-way."""

from __future__ import annotations

import httpx
from fastapi.testclient import TestClient

from mapservice.api.app import create_app
from mapservice.robot import api_client
from mapservice.runtime.secrets import ADMIN_TOKEN_FILE, WRITER_TOKEN_FILE, local_secret
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore


def test_token_from_flag_then_environment_then_the_data_dir(monkeypatch, tmp_path) -> None:
    """--token wins, then MAPSERVICE_API_TOKEN, then the writer token `mapservice up` generated in MAPSERVICE_DATA_DIR; none: None."""
    monkeypatch.setenv("MAPSERVICE_DATA_DIR", str(tmp_path))
    assert api_client.writer_token() is None and api_client.admin_token() is None
    generated = local_secret(tmp_path, WRITER_TOKEN_FILE)
    admin = local_secret(tmp_path, ADMIN_TOKEN_FILE)
    assert api_client.writer_token() == generated and api_client.admin_token() == admin
    monkeypatch.setenv("MAPSERVICE_API_TOKEN", "from-env")
    assert api_client.writer_token() == "from-env"
    assert api_client.writer_token("from-flag") == "from-flag"


def test_the_client_sends_the_token_and_waits_out_429() -> None:
    """Requests carry 'Authorization: Bearer <token>'; a 429 is retried after its Retry-After, not raised."""
    seen, answers = [], [429, 429, 200]

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request.headers.get("authorization"))
        status = answers.pop(0)
        return httpx.Response(
            status,
            headers={"Retry-After": "0"} if status == 429 else {},
            json={"ok": status == 200},
        )

    with api_client.api_client(
        "http://service", "robot-token", transport=httpx.MockTransport(handler)
    ) as client:
        r = client.get("/api/chunk-service/meta")
    assert r.status_code == 200 and seen == ["Bearer robot-token"] * 3


def test_a_real_service_rate_limit_is_waited_out() -> None:
    """Against the API with a 2-per-second limit, five requests in a row all get through (after 429s)."""
    settings = Settings(admin_token="a" * 32, api_writer_tokens="w" * 32, api_rate_limit="2/second")
    service = TestClient(create_app(settings, MemoryStore(), {}))._transport
    statuses = []

    def counting(request: httpx.Request) -> httpx.Response:
        response = service.handle_request(request)
        statuses.append(response.status_code)
        return response

    with api_client.api_client(
        "http://testserver", "w" * 32, transport=httpx.MockTransport(counting)
    ) as client:
        assert all(client.get("/api/v1/stats").status_code == 200 for _ in range(5))
    assert 429 in statuses and statuses.count(200) == 5
