"""/metrics on the gateway's and processors' health port follows the API's metrics rule."""

from __future__ import annotations

import urllib.error
import urllib.request

import pytest
from pydantic import SecretStr

from mapservice.runtime.health_server import serve_health
from mapservice.runtime.metrics_gate import metrics_gate
from mapservice.settings import Settings

METRICS, ADMIN = "m" * 40, "a" * 40


def settings(access: str) -> Settings:
    return Settings(
        api_metrics_access=access,
        api_metrics_token=SecretStr(METRICS),
        admin_token=SecretStr(ADMIN),
        api_writer_tokens=SecretStr("w" * 40),
    )


@pytest.mark.parametrize(
    "access, header, expected",
    [
        ("open", None, None),
        ("off", f"Bearer {METRICS}", 404),
        ("token", None, 401),
        ("token", "Bearer nope", 401),
        ("token", f"Basic {METRICS}", 401),
        ("token", f"Bearer {'w' * 40}", 401),  # a writer token opens no metrics
        ("token", f"Bearer {METRICS}", None),
        ("token", f"bearer {ADMIN}", None),
    ],
)
def test_the_gate_opens_metrics_only_to_the_metrics_or_admin_token(
    access, header, expected
) -> None:
    """open serves all, off answers 404, token needs the metrics or the admin bearer token."""
    refusal = metrics_gate(settings(access))(header)
    assert (refusal and refusal[0]) == expected, refusal


def test_production_defaults_to_token_protected_metrics() -> None:
    """Without the setting, production mode guards /metrics and local mode leaves it open."""
    prod = Settings(
        mode="production",
        admin_token=SecretStr(ADMIN),
        clickhouse_dsn="chdb:///x",
        api_metrics_token=SecretStr(METRICS),
    )
    assert metrics_gate(prod)(None)[0] == 401
    assert metrics_gate(Settings())(None) is None


def get(port: int, path: str, token: str | None = None) -> tuple[int, bytes]:
    req = urllib.request.Request(
        f"http://127.0.0.1:{port}{path}",
        headers={"Authorization": f"Bearer {token}"} if token else {},
    )
    try:
        with urllib.request.urlopen(req, timeout=5) as resp:
            return resp.status, resp.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def test_the_health_port_guards_metrics_but_never_the_probes() -> None:
    """A component's /metrics answers 401 without the token, 200 with it; /healthz and /readyz stay open to the kubelet."""
    server = serve_health(
        "127.0.0.1", 0, lambda: {"ok": True}, metrics_gate=metrics_gate(settings("token"))
    )
    port = server.server_address[1]
    try:
        code, body = get(port, "/metrics")
        assert code == 401 and b"MAPSERVICE_API_METRICS_TOKEN" in body
        code, body = get(port, "/metrics", METRICS)
        assert code == 200 and b"python_info" in body
        assert get(port, "/healthz")[0] == 200 and get(port, "/readyz")[0] == 200
    finally:
        server.shutdown()
