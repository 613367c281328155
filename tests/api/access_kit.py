"""What the API access tests share: one token of each kind, an app over memory with them,
and the Authorization header for a credential by its name."""

from __future__ import annotations

from fastapi import FastAPI

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
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
