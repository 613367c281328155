"""The incident alerts' webhooks end to end: Mosquitto, the embedded Kafka and ClickHouse,
the gateway, and `mapservice serve` (processors + API), with a local HTTP receiver that is
slow, then down, then back, then answering wrong.

An operator registers the receiver through the API and keeps the secret it answers with.
Robots report low batteries (a `battery_low` incident each, and an `offline` one once they
fall silent) while the receiver is slow and while it is down: their poses are stored at
once all the same, and the webhook pauses with the reason the API lists. Once the receiver
is back and the webhook resumed, every incident found so far has reached it, each delivery
signed with the secret. Then it answers 4xx and 5xx: paused again, saying so; resumed once
it answers 2xx, it gets the incidents found meanwhile.
"""

from __future__ import annotations

import json
import time

import httpx
import pytest

from mapservice.core.webhooks import verify
from mapservice.core.wire2019 import encode_coordinates, format_timestamp
from mapservice.local.embedded import free_port
from tests.processors.test_webhook_delivery import Receiver

from .conftest import start_stack, wait_for_count
from .test_pipeline import now_ms, publish_all

OPERATOR = "operator-" + "p" * 32
ENV = {
    "MAPSERVICE_API_OPERATOR_TOKENS": OPERATOR,
    "MAPSERVICE_WEBHOOK_REGISTRY_POLL_S": "0.5",
    "MAPSERVICE_WEBHOOK_NETWORKS": "127.0.0.0/8",  # the receivers run on this machine
    "MAPSERVICE_WEBHOOK_TIMEOUT_S": "1",
    "MAPSERVICE_WEBHOOK_MAX_TRIES": "3",
    "MAPSERVICE_WEBHOOK_BACKOFF_CAP_S": "2",
    "MAPSERVICE_ROBOT_OFFLINE_AFTER_S": "3",
}
AUTH = {"Authorization": f"Bearer {OPERATOR}"}


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    stack = start_stack(tmp_path_factory, "mosquitto", extra_env=ENV)
    yield stack
    stack.stop()


def api(stack, method: str, path: str, **kwargs) -> httpx.Response:
    return httpx.request(
        method, f"{stack.api_url}/api/v1/webhooks{path}", headers=AUTH, timeout=30, **kwargs
    )


def listed(stack, webhook_id: str) -> dict:
    r = api(stack, "GET", "")
    assert r.status_code == 200, r.text
    return next(w for w in r.json()["webhooks"] if w["id"] == webhook_id)


def wait_until(condition, what: str, timeout_s: float = 60.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if found := condition():
            return found
        time.sleep(0.25)
    raise AssertionError(f"timed out waiting for {what}")


def low_batteries(stack, prefix: str, robots: int, since: int) -> None:
    """Each robot reports twice with 10 % battery (a battery_low incident), then falls
    silent (an offline one); its poses are stored within seconds whatever the receiver does."""
    messages = [
        (
            f"iot/coordinates/{prefix}-{r}",
            encode_coordinates(
                f"{prefix}-{r}",
                format_timestamp(since + k * 500 + r),
                1.0 + r,
                2.0,
                battery_level=10.0,
            ),
        )
        for r in range(robots)
        for k in range(2)
    ]
    started = time.monotonic()
    publish_all(stack, messages)
    stored = wait_for_count(stack, "pose", f"{prefix}-", since - 1, since + 60_000, 2 * robots, 20)
    assert len(stored) == 2 * robots, stored
    assert time.monotonic() - started < 20


def incident_ids(stack, prefix: str, since: int) -> set[str]:
    rows = httpx.get(
        f"{stack.api_url}/api/v1/incidents",
        params={"from": since - 1, "to": now_ms() + 60_000},
        timeout=30,
    ).json()["incidents"]
    return {i["id"] for i in rows if i["robots"][0].startswith(f"{prefix}-")}


def delivered_ids(requests: list, secret: str) -> set[str]:
    """The incidents of the deliveries a receiver answered 2xx, each checked authentic."""
    ids = set()
    for _, headers, body in requests:
        assert verify(secret, headers, body, time.time()), headers
        ids.add(json.loads(body)["id"])
    return ids


def paused_then_resumed(stack, receiver: Receiver, hook: str, secret: str, wrong: int) -> None:
    """The receiver answers `wrong`: the webhook pauses, saying so; answering 2xx again and
    resumed, it gets the incidents found meanwhile."""
    receiver.mode = wrong
    prefix, at = f"wrong{wrong}", now_ms() - 5_000
    low_batteries(stack, prefix, 2, at)
    paused = wait_until(
        lambda: (w := listed(stack, hook))["state"] == "paused" and w, f"the {wrong} pause"
    )
    assert f"HTTP {wrong}" in paused["pausedReason"], paused
    assert paused["lastResult"] == f"HTTP {wrong}"
    receiver.requests.clear()  # none is sent while paused
    receiver.mode = "ok"
    assert api(stack, "POST", f"/{hook}/resume", json={}).status_code == 202
    wanted = wait_until(
        lambda: len(ids := incident_ids(stack, prefix, at)) >= 4 and ids,
        f"the incidents of {prefix}",
    )
    wait_until(
        lambda: wanted <= delivered_ids(receiver.requests, secret),
        f"the incidents of {prefix} delivered",
    )


def test_every_incident_reaches_a_receiver_that_was_slow_down_and_wrong(stack) -> None:
    port = free_port()
    receiver = Receiver(port, "slow")
    try:
        r = api(stack, "POST", "", json={"url": f"http://127.0.0.1:{port}/hook"})
        assert r.status_code == 201, r.text
        hook, secret = r.json()["id"], r.json()["secret"]
        # Taken up once the processors report it (they re-read the registry every 0.5 s).
        wait_until(lambda: listed(stack, hook)["replicas"] == 1, "the processors' first report")
        assert listed(stack, hook)["state"] == "active"
        since = now_ms() - 5_000

        # Slow (answers after the timeout), then down: the poses are stored at once all
        # the same, and the webhook pauses saying why.
        low_batteries(stack, "slow", 3, since)
        wait_until(lambda: receiver.requests, "a try at the slow receiver")
        receiver.close()
        low_batteries(stack, "down", 3, since + 2_000)
        paused = wait_until(
            lambda: (w := listed(stack, hook))["state"] == "paused" and w, "the pause"
        )
        assert "3 tries" in paused["pausedReason"], paused
        assert any(e in paused["pausedReason"] for e in ("ConnectError", "no answer within"))
        assert paused["failedTries"] >= 3 and paused["replicas"] == 1
        found = wait_until(
            lambda: (
                len(ids := incident_ids(stack, "slow", since) | incident_ids(stack, "down", since))
                >= 12
                and ids
            ),
            "a battery_low and an offline incident of each robot",
        )

        # Back, and resumed: every incident found so far reaches it, signed.
        receiver = Receiver(port, "ok")
        assert api(stack, "POST", f"/{hook}/resume", json={}).status_code == 202
        wait_until(
            lambda: found <= delivered_ids(receiver.requests, secret), "every incident delivered"
        )
        active = wait_until(
            lambda: (w := listed(stack, hook))["state"] == "active" and w["queued"] == 0 and w,
            "the webhook active again",
        )
        assert active["delivered"] >= len(found) and active["lastResult"] == "delivered"

        # Wrong answers: paused again, saying so; resumed, it gets what was found meanwhile.
        for wrong in (404, 503):
            paused_then_resumed(stack, receiver, hook, secret, wrong)
        assert listed(stack, hook)["state"] == "active"

        # Removed: nothing more is sent to it.
        assert api(stack, "DELETE", f"/{hook}").status_code == 204
        time.sleep(1.5)  # three polls of the registry
        receiver.requests.clear()
        low_batteries(stack, "after", 1, now_ms() - 5_000)
        time.sleep(2.0)
        assert receiver.requests == []
    finally:
        receiver.close()
