"""Schemathesis over the whole OpenAPI document: no generated request gets a 5xx, and every
refusal says why.

Each operation gets a fixed budget of generated cases (MAPSERVICE_FUZZ_API_EXAMPLES,
default 100: about 2,700 requests over the 27 operations) against the app over an in-memory
store with a week of data in it, as an administrator so that the destructive and writing
operations are exercised too. In CI the generation is derandomized, so a failure reproduces;
run it locally with a random seed to explore. Whatever it ever finds becomes a regression
test in the router's own test file.
"""

from __future__ import annotations

import os

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import not_a_server_error

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.settings import Settings
from mapservice.testing.memory_publisher import MemoryPublisher
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import EventFactory

NOW = 1_795_255_200_000  # 2026-11-21T10:00:00Z
ADMIN_TOKEN = "fuzz-admin-" + "0" * 32
EXAMPLES = int(os.environ.get("MAPSERVICE_FUZZ_API_EXAMPLES", "100"))


def _store() -> MemoryStore:
    ev = EventFactory()
    store = MemoryStore()
    store.append([ev.meta(NOW - 86_400_000)])
    for i in range(20):
        store.append(
            [
                ev.pose(f"r{i % 3}", NOW - i * 60_000, x=float(i)),
                ev.chunk(f"r{i % 2}", NOW - i * 90_000, i % 4, i % 5, bytes([i]) * 10_000),
            ]
        )
    store.append_dead_letters([ev.dead_letter()])
    return store


# As administrator (every scope), without the rate limit: the fuzzer is one fast client;
# with a webhook signing key, so that webhooks are registered (without one: 503, by design).
# Built at import, before the tests' environment: its host name named here.
APP = create_app(
    Settings(
        admin_token=ADMIN_TOKEN,
        api_rate_limit="",
        api_allowed_hosts=["testserver"],
        webhook_signing_key="fuzz-signing-key-" + "0" * 32,
    ),
    _store(),
    {"kafka": lambda: True},
    ManualClock(NOW),
    publisher=MemoryPublisher(),
)
schema = schemathesis.openapi.from_asgi("/openapi.json", APP)


def refusal_says_why(ctx, response, case) -> None:
    """A 4xx reply carries a non-empty reason a person can read."""
    if 400 <= response.status_code < 500:
        body = response.text.strip()
        assert body, f"{case.method} {case.path} -> {response.status_code} with an empty body"


@schema.parametrize()
@settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=os.environ.get("CI") == "true",
    suppress_health_check=list(HealthCheck),
    database=None,
)
def test_no_generated_request_gets_a_server_error(case) -> None:
    """Every operation answers generated input with a non-5xx status, and refusals say why."""
    response = case.call(headers={"Authorization": f"Bearer {ADMIN_TOKEN}"})
    case.validate_response(response, checks=[not_a_server_error], excluded_checks=[])
    refusal_says_why(None, response, case)


def test_the_fuzzer_reaches_every_operation() -> None:
    """The OpenAPI document the fuzzer reads lists every route the app serves."""
    operations = {
        (op.method.upper(), op.path)
        for op in (result.ok() for result in schema.get_all_operations())
    }
    routes = {
        (method, route.path)
        for route in APP.routes
        for method in getattr(route, "methods", None) or ()
        if getattr(route, "include_in_schema", False) and method != "HEAD"
    }
    assert routes <= operations, routes - operations
    assert len(operations) >= 25


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
