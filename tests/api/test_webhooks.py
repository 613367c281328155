"""The incident alerts' webhooks through the API: only operators (and the admin) manage
them, readers, writers and robots are refused saying why; a URL or kind that cannot be
delivered to is refused with a message; the cap; the secret shown at registration is the
one derived from the signing key (and verifies a delivery signed as the processors sign
it); removal, resume, and the list's state folded from the processors' reports."""

from __future__ import annotations

import time

import pytest
from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.core.webhook_registry import WEBHOOK_ID, WebhookReport
from mapservice.core.webhooks import derived_secret, signed_headers, verify
from mapservice.testing.memory_store import MemoryStore
from tests.api.access_kit import (
    ADMIN_TOKEN,
    NOW,
    OPERATOR_TOKEN,
    READER_TOKEN,
    ROBOT_TOKENS,
    WRITER_TOKENS,
    settings_for,
)

OPERATOR, READER, WRITER, ADMIN = OPERATOR_TOKEN, READER_TOKEN, WRITER_TOKENS[0], ADMIN_TOKEN
ROBOT = ROBOT_TOKENS["agv-7"]
KEY = "signing-key-" + "k" * 32
URL = "https://mes.plant.example:8443/hooks/incidents?line=3"
# api/routers/webhooks.py's operations (tests/api/test_api.py expects them in the document)
WEBHOOK_OPERATION_IDS = {
    "registerWebhook",
    "listWebhooks",
    "showWebhookSecret",
    "removeWebhook",
    "resumeWebhook",
}


class World:
    def __init__(self, **settings) -> None:
        self.settings = settings_for("open", **{"webhook_signing_key": KEY, **settings})
        self.store = MemoryStore()
        self.clock = ManualClock(NOW)
        self.client = TestClient(create_app(self.settings, self.store, {}, self.clock))

    def call(self, method: str, path: str, token: str | None = OPERATOR, **kwargs):
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        return self.client.request(method, "/api/v1/webhooks" + path, headers=headers, **kwargs)

    def register(self, body: dict | None = None, token: str | None = OPERATOR):
        return self.call("POST", "", token, json=body if body is not None else {"url": URL})

    def listed(self) -> list[dict]:
        r = self.call("GET", "")
        assert r.status_code == 200, r.text
        return r.json()["webhooks"]


@pytest.mark.parametrize("token", [READER, WRITER, ROBOT, None, "wrong-" + "x" * 32])
def test_only_operators_and_the_admin_manage_webhooks(token) -> None:
    w = World()
    created = w.register().json()
    for method, path, kwargs in (
        ("POST", "", {"json": {"url": URL}}),
        ("GET", "", {}),
        ("GET", f"/{created['id']}/secret", {}),
        ("POST", f"/{created['id']}/resume", {"json": {}}),
        ("DELETE", f"/{created['id']}", {}),
    ):
        r = w.call(method, path, token, **kwargs)
        assert r.status_code == (401 if token is None or token.startswith("wrong") else 403)
        if r.status_code == 403:
            assert "managing the incident alerts' webhooks" in r.json()["detail"]
            assert "needs an operator or admin token" in r.json()["detail"]
    assert [h["id"] for h in w.listed()] == [created["id"]]
    assert w.register(token=ADMIN).status_code == 201


def test_a_registered_webhook_is_listed_with_its_derived_secret_shown_once_and_on_request() -> None:
    w = World()
    r = w.register({"url": URL, "kinds": ["stuck", "near_miss", "stuck"]})
    assert r.status_code == 201, r.text
    created = r.json()
    assert WEBHOOK_ID.fullmatch(created["id"])
    assert created["secret"] == derived_secret(KEY, created["id"])
    assert created["kinds"] == ["near_miss", "stuck"] and created["url"] == URL
    assert created["createdBy"].startswith("operator:") and created["created_ms"] == NOW
    assert created["state"] == "active" and created["replicas"] == 0
    (listed,) = w.listed()
    assert "secret" not in listed  # only at registration and on request
    assert listed == {k: v for k, v in created.items() if k != "secret"}
    shown = w.call("GET", f"/{created['id']}/secret").json()
    assert shown == {"id": created["id"], "secret": created["secret"]}
    # No table holds the secret: the registry keeps what the processors need to derive it.
    assert created["secret"] not in repr(w.store.webhooks())
    # The secret verifies what the processors sign for this webhook, and another's does not.
    body, now = b'{"kind": "stuck"}', int(time.time())
    headers = signed_headers(derived_secret(KEY, created["id"]), now, body)
    assert verify(created["secret"], headers, body, now)
    other = w.register().json()
    assert other["secret"] != created["secret"]
    assert not verify(other["secret"], headers, body, now)


def test_a_new_signing_key_gives_every_webhook_a_new_secret() -> None:
    w = World()
    created = w.register().json()
    again = World(webhook_signing_key="another-key-" + "q" * 32)
    again.store = w.store
    again.client = TestClient(create_app(again.settings, w.store, {}, w.clock))
    shown = again.call("GET", f"/{created['id']}/secret").json()["secret"]
    assert shown != created["secret"]
    assert shown == derived_secret("another-key-" + "q" * 32, created["id"])


@pytest.mark.parametrize(
    "body, says",
    [
        ({"url": "ftp://plant.example/x"}, "http:// or https://"),
        ({"url": "https://user:pw@plant.example/x"}, "must not hold credentials"),
        ({"url": "https:///no-host"}, "no valid host"),
        ({"url": "https://plant.example/x#frag"}, "fragment"),
        ({"url": "https://plant.example:0/x"}, "port"),
        ({"url": "https://plant.example/a b"}, "whitespace"),
        ({"url": "https://plant.example/" + "a" * 2048}, "at most 2048"),
        ({"url": URL, "kinds": ["fire"]}, "near_miss"),
        ({"url": URL, "kinds": "stuck"}, "valid list"),
        ({"url": URL, "kinds": ["stuck"] * 11}, "at most 10"),
        ({"kinds": ["stuck"]}, "url"),
        ({"url": 5}, "valid string"),
    ],
)
def test_a_webhook_that_cannot_be_delivered_to_is_refused_with_a_message(body, says) -> None:
    w = World()
    r = w.register(body)
    assert r.status_code == 422, r.text
    assert says in r.text
    assert w.store.webhooks() == []


def test_the_cap_refuses_one_more_until_one_is_removed() -> None:
    w = World(webhooks_max=2)
    first, _ = (w.register().json() for _ in range(2))
    r = w.register()
    assert r.status_code == 409 and "MAPSERVICE_WEBHOOKS_MAX" in r.json()["detail"]
    assert len(w.listed()) == 2
    assert w.call("DELETE", f"/{first['id']}").status_code == 204
    assert w.register().status_code == 201
    assert World(webhooks_max=0).register().status_code == 409


def test_without_a_signing_key_no_webhook_is_registered_and_why_is_said() -> None:
    w = World(webhook_signing_key="")
    r = w.register()
    assert r.status_code == 503 and "MAPSERVICE_WEBHOOK_SIGNING_KEY" in r.json()["detail"]
    assert w.store.webhooks() == []


def test_remove_and_resume_name_a_registered_webhook() -> None:
    w = World()
    created = w.register().json()
    unknown = "wh-" + "0" * 16
    for method, path in (("DELETE", f"/{unknown}"), ("POST", f"/{unknown}/resume")):
        r = w.call(method, path, json={} if method == "POST" else None)
        assert r.status_code == 404 and unknown in r.json()["detail"]
    assert w.call("GET", f"/{unknown}/secret").status_code == 404
    assert w.call("DELETE", "/not-an-id").status_code == 422
    w.clock.advance(5_000)
    r = w.call("POST", f"/{created['id']}/resume", json={})
    assert r.status_code == 202 and r.json()["resumed_ms"] == NOW + 5_000
    assert w.store.webhooks()[0].resumed_ms == NOW + 5_000  # what the processors act on
    assert w.call("DELETE", f"/{created['id']}").status_code == 204
    assert w.listed() == []
    assert w.call("DELETE", f"/{created['id']}").status_code == 404


def test_the_list_folds_the_fresh_reports_of_the_processors_replicas() -> None:
    w = World(webhook_registry_poll_s=5.0)
    hook = w.register().json()["id"]
    paused = "a delivery failed 6 tries in a row; last: HTTP 500"
    w.store.report_webhooks(
        [
            WebhookReport(hook, "a:1", NOW, "", "", NOW - 2_000, "delivered", 7, 0, 0, 0),
            WebhookReport(
                hook, "b:2", NOW, paused, "HTTP 500", NOW - 1_000, "HTTP 500", 3, 6, 1, 4
            ),
            # a replica gone a while ago: its pause is no one's now
            WebhookReport(hook, "c:3", NOW - 61_000, "gone", "x", NOW - 61_000, "x", 100, 1, 0, 0),
        ]
    )
    (listed,) = w.listed()
    assert listed["state"] == "paused" and listed["pausedReason"] == paused
    assert listed["lastTry_ms"] == NOW - 1_000 and listed["lastResult"] == "HTTP 500"
    assert listed["lastError"] == "HTTP 500"
    assert (listed["delivered"], listed["failedTries"], listed["dropped"], listed["queued"]) == (
        10,
        6,
        1,
        4,
    )
    assert listed["replicas"] == 2
    w.store.report_webhooks(
        [WebhookReport(hook, "b:2", NOW + 1, "", "HTTP 500", NOW + 1, "delivered", 8, 6, 1, 0)]
    )
    (listed,) = w.listed()
    assert listed["state"] == "active" and listed["lastResult"] == "delivered"
