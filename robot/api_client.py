"""How the robot-side commands reach the service's REST API: with a bearer token (the only
thing a 2019 robot needs to add) and, when the service says 429, again after Retry-After.

The token: --token, else MAPSERVICE_API_TOKEN, else the one `mapservice up` generated in
its data dir (MAPSERVICE_DATA_DIR, default .mapservice-data), so a robot started next to
`make up` needs no setup.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import httpx

from mapservice.runtime.secrets import ADMIN_TOKEN_FILE, WRITER_TOKEN_FILE, stored_secret

TOKEN_ENV = "MAPSERVICE_API_TOKEN"
MAX_RETRIES = 8
MAX_WAIT_S = 30.0


def data_dir() -> Path:
    return Path(os.environ.get("MAPSERVICE_DATA_DIR", ".mapservice-data"))


def writer_token(explicit: str | None = None) -> str | None:
    """The writer (robot) token to send, or None (then writes are refused with 401)."""
    return explicit or os.environ.get(TOKEN_ENV) or stored_secret(data_dir(), WRITER_TOKEN_FILE)


def admin_token(explicit: str | None = None) -> str | None:
    """The admin token to send, or None."""
    return (
        explicit
        or os.environ.get("MAPSERVICE_ADMIN_TOKEN")
        or stored_secret(data_dir(), ADMIN_TOKEN_FILE)
    )


class RetryAfter(httpx.BaseTransport):
    """Sends a request again when the service answers 429, after the Retry-After it names
    (bounded): a robot uploading a whole map goes as fast as the rate limit lets it."""

    def __init__(self, inner: httpx.BaseTransport | None = None) -> None:
        self.inner = inner or httpx.HTTPTransport()

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        for _ in range(MAX_RETRIES):
            response = self.inner.handle_request(request)
            if response.status_code != 429:
                return response
            try:
                wait = float(response.headers.get("retry-after", "1"))
            except ValueError:
                wait = 1.0
            response.close()
            time.sleep(min(max(wait, 0.1), MAX_WAIT_S))
        return self.inner.handle_request(request)

    def close(self) -> None:
        self.inner.close()


def api_client(
    base_url: str,
    token: str | None,
    timeout: float = 30.0,
    transport: httpx.BaseTransport | None = None,
) -> httpx.Client:
    """An httpx client for the service's API that sends `token` as a bearer credential."""
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    return httpx.Client(
        base_url=base_url.rstrip("/"),
        timeout=timeout,
        headers=headers,
        transport=RetryAfter(transport),
    )
