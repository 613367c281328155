"""Webhook deliveries against a local receiver that is slow (answers after the timeout),
down (connection refused) or wrong (4xx, 5xx): the processors store every batch at their
pace meanwhile, each failed try waits longer than the one before, the webhook pauses with
its reason, and once the receiver is back a resume delivers every incident found, signed.
The queue's bound drops the oldest and counts it."""

from __future__ import annotations

import dataclasses
import http.server
import json
import socket
import threading
import time

import pytest

from mapservice.adapters.webhook_destinations import DestinationPolicy
from mapservice.core.webhooks import DELIVERY_HEADER, Webhook, backoff_s, parse_networks, verify
from mapservice.local.embedded import free_port
from mapservice.processors.views import LiveViews
from mapservice.processors.webhook_delivery import DELIVERIES, DeliveryPolicy, WebhookDeliveries
from mapservice.settings import Settings
from tests.processors.test_incident_watch import PATH, Floor

SECRET = "s3cret-for-the-plant-0123"
# A batch of four poses takes milliseconds to store: one that waited for a try would take
# the timeout, far beyond what a loaded machine adds.
# The receivers are on this machine: its loopback network is named, as a plant names its own.
POLICY = DeliveryPolicy(
    timeout_s=1.0,
    max_tries=3,
    backoff_base_s=0.1,
    backoff_cap_s=0.25,
    max_queued=1000,
    destinations=DestinationPolicy(networks=parse_networks("127.0.0.0/8")),
)


class Receiver:
    """An HTTP server on 127.0.0.1 answering as `mode` says: "ok" (204), "slow" (after the
    delivery timeout), or a status code. Keeps every request: (monotonic, headers, body)."""

    def __init__(self, port: int, mode: str | int = "ok") -> None:
        self.mode = mode
        self.requests: list[tuple[float, dict[str, str], bytes]] = []
        receiver = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 - the stdlib's name
                body = self.rfile.read(int(self.headers["Content-Length"]))
                receiver.requests.append((time.monotonic(), dict(self.headers), body))
                if receiver.mode == "slow":
                    time.sleep(POLICY.timeout_s * 3)
                code = 204 if receiver.mode in ("ok", "slow") else int(receiver.mode)
                self.send_response(code)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *args: object) -> None:
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", port), Handler)
        self.server.daemon_threads = True
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()

    def delivered(self) -> dict[str, dict]:
        """The alerts it answered 2xx to, by incident and event, checked authentic."""
        out = {}
        for _, headers, body in self.requests:
            assert verify(SECRET, headers, body, time.time())
            doc = json.loads(body)
            out[(doc["id"], doc["event"], doc["found_ms"])] = doc
        return out


class WebhookFloor(Floor):
    """The incident floor of test_incident_watch.py, its live views delivering to webhooks."""

    def __init__(self, webhooks: WebhookDeliveries) -> None:
        self.webhooks = webhooks
        super().__init__()

    def start(self) -> None:
        super().start()
        views = LiveViews(
            Settings(),
            history=self.store,
            annotations=self.store,
            conflicts=self.store,
            incidents=self.store,
            commands=self.store,
            vda=self.store,
            writer=self.store,
            advertiser=None,
            store_thread=self.consumer.sink.thread,
            now_ms=lambda: self.now,
            webhooks=self.webhooks,
        )
        views.load()
        self.views = self.consumer.views = views

    def run(self, ev, seconds: int) -> list[float]:
        """`seconds` of four robots (stuck, near miss, battery low); each batch's store time."""
        took = []
        for t in range(seconds):
            start = time.monotonic()
            self.send(
                ev,
                ("s", t, 5.0 if t < 40 else 5.0 + t - 40, 5.0, 80.0, PATH),
                ("a", t, float(t) * 0.5, 0.0, 80.0, PATH),
                ("b", t, 15.0, 0.5, 80.0, None),
                ("c", t, 20.0, 20.0, 20.0 - t * 0.25, None),
            )
            took.append(time.monotonic() - start)
        return took


def wait_for(condition, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


FAILURES = ["slow", "down", 400, 401, 404, 410, 429, 500, 502, 503]


@pytest.mark.parametrize("failure", FAILURES, ids=str)
def test_a_failing_receiver_neither_slows_the_pipeline_nor_loses_an_alert(ev, failure) -> None:
    port = free_port()
    receiver = None if failure == "down" else Receiver(port, failure)
    deliveries = WebhookDeliveries(POLICY)
    deliveries.set_webhooks([Webhook("w1", f"http://127.0.0.1:{port}/hook", SECRET)])
    deliveries.start()
    try:
        floor = WebhookFloor(deliveries)
        took = floor.run(ev, 60)
        # The store's pace: no batch waited for a delivery (one try alone takes the timeout).
        assert max(took) < POLICY.timeout_s, max(took)
        wait_for(lambda: deliveries.health()["w1"].state == "paused")
        health = deliveries.health()["w1"]
        reason = {"slow": "no answer within 1 s", "down": "ConnectError"}.get(
            failure, f"HTTP {failure}"
        )
        assert (
            reason in health.paused_reason and f"{POLICY.max_tries} tries" in health.paused_reason
        )
        assert health.delivered == 0 and health.failed_tries == POLICY.max_tries
        # while paused, nothing is tried and the alerts wait
        tried = len(receiver.requests) if receiver else 0
        time.sleep(POLICY.backoff_cap_s * 2)
        assert (len(receiver.requests) if receiver else 0) == tried
        assert deliveries.queued("w1") > 0
        if receiver is not None:
            # one delivery at a time, each try after a longer wait (its id stays)
            times = [
                t
                for t, h, _ in receiver.requests
                if h[DELIVERY_HEADER] == receiver.requests[0][1][DELIVERY_HEADER]
            ]
            assert len(times) == POLICY.max_tries
            for n, (a, b) in enumerate(zip(times, times[1:], strict=False), start=1):
                wait = backoff_s(n, POLICY.backoff_base_s, POLICY.backoff_cap_s)
                assert b - a >= wait * 0.9, (n, b - a, wait)
        # the receiver is back: a resume delivers every alert found, signed
        if receiver is None:
            receiver = Receiver(port)
        receiver.mode = "ok"
        receiver.requests.clear()
        assert deliveries.resume("w1")
        wait_for(lambda: deliveries.queued("w1") == 0)
        got = receiver.delivered()
        announced = {a["id"] for a in got.values()}
        assert {i.incident_id for i in floor.stored()} <= announced
        assert {a["kind"] for a in got.values()} == {"stuck", "near_miss", "battery_low"}
        assert deliveries.health()["w1"].state == "active"
    finally:
        deliveries.close()
        if receiver is not None:
            receiver.close()


def test_only_the_kinds_a_webhook_asks_for_are_sent_to_it(ev) -> None:
    port = free_port()
    receiver = Receiver(port)
    deliveries = WebhookDeliveries(POLICY)
    url = f"http://127.0.0.1:{port}/"
    deliveries.set_webhooks(
        [Webhook("all", url, SECRET), Webhook("stuck", url, SECRET, frozenset({"stuck"}))]
    )
    deliveries.start()
    try:
        WebhookFloor(deliveries).run(ev, 60)
        wait_for(lambda: deliveries.queued("all") == deliveries.queued("stuck") == 0)
        by_hook: dict[str, set[str]] = {}
        for _, headers, body in receiver.requests:
            by_hook.setdefault(headers["X-Mapservice-Webhook"], set()).add(json.loads(body)["kind"])
        assert by_hook == {"all": {"stuck", "near_miss", "battery_low"}, "stuck": {"stuck"}}
    finally:
        deliveries.close()
        receiver.close()


def test_a_full_queue_drops_the_oldest_and_counts_it() -> None:
    deliveries = WebhookDeliveries(DeliveryPolicy(max_queued=5))  # not started: nothing sent
    deliveries.set_webhooks([Webhook("w", "http://127.0.0.1:9/", SECRET)])
    dropped = DELIVERIES.labels("dropped")._value.get()
    for n in range(8):
        assert deliveries.offer({"kind": "stuck", "n": n}) == 1
    assert deliveries.queued("w") == 5
    assert deliveries.health()["w"].dropped == 3
    assert DELIVERIES.labels("dropped")._value.get() - dropped == 3
    kept = [json.loads(d.body)["n"] for d in deliveries._hooks["w"].queue]
    assert kept == [3, 4, 5, 6, 7]
    deliveries.set_webhooks([])  # removed: its deliveries go with it
    assert deliveries.queued("w") == 0 and deliveries.offer({"kind": "stuck"}) == 0
    deliveries.close()


def test_a_receiver_back_before_the_tries_run_out_gets_everything_without_a_resume(ev) -> None:
    port = free_port()
    patient = dataclasses.replace(POLICY, max_tries=6, backoff_base_s=0.2, backoff_cap_s=1.0)
    deliveries = WebhookDeliveries(patient)
    deliveries.set_webhooks([Webhook("w1", f"http://127.0.0.1:{port}/", SECRET)])
    deliveries.start()
    receiver = None
    try:
        floor = WebhookFloor(deliveries)
        floor.run(ev, 60)
        wait_for(lambda: deliveries.health()["w1"].failed_tries >= 2)  # down: refused twice
        receiver = Receiver(port)  # back
        wait_for(lambda: deliveries.queued("w1") == 0)
        health = deliveries.health()["w1"]
        assert health.state == "active" and health.failed_tries < patient.max_tries
        announced = {a["id"] for a in receiver.delivered().values()}
        assert {i.incident_id for i in floor.stored()} <= announced
    finally:
        deliveries.close()
        if receiver is not None:
            receiver.close()


def started(
    webhooks: list[Webhook], policy: DeliveryPolicy = POLICY, alerts: int = 0
) -> WebhookDeliveries:
    """Deliveries to `webhooks` under `policy`, started, with `alerts` stuck alerts offered."""
    deliveries = WebhookDeliveries(policy)
    deliveries.set_webhooks(webhooks)
    deliveries.start()
    for n in range(alerts):
        deliveries.offer({"event": "new", "found_ms": n, "id": f"i{n}", "kind": "stuck"})
    return deliveries


def test_a_url_the_client_cannot_send_to_fails_its_tries_and_the_worker_goes_on() -> None:
    """A stored URL the delivery client cannot parse (one registered before the API checked
    it with that parser): its tries fail with the reason, and the one worker still delivers
    to the other webhook (a worker that died would have stopped every webhook)."""
    port = free_port()
    receiver = Receiver(port)
    deliveries = started(
        [
            Webhook("bad", f"http://0177.0.0.1:{port}/", SECRET),
            Webhook("good", f"http://127.0.0.1:{port}/", SECRET),
        ],
        dataclasses.replace(POLICY, workers=1),
        alerts=3,
    )
    try:
        wait_for(lambda: deliveries.health()["bad"].paused_reason)
        assert "InvalidURL" in deliveries.health()["bad"].paused_reason
        wait_for(lambda: deliveries.queued("good") == 0)
        assert len(receiver.delivered()) == 3
    finally:
        deliveries.close()
        receiver.close()


# How a hostile or broken receiver can answer: (sent at once, then a byte every 0.2 s,
# then 64 KiB pieces without end or not). A status arrives at once only where it is 500.
OK, FAILED = b"HTTP/1.1 200 OK\r\n", b"HTTP/1.1 500 Oops\r\n"
ANSWERS = {
    "trickled status line": (b"", OK + b"Content-Length: 0\r\n\r\n", False),
    "trickled header without end": (OK, b"X-Pad: " + b"a" * 100_000, False),
    "endless body": (FAILED + b"Content-Length: 100000000000\r\n\r\n", b"", True),
    "trickled body": (FAILED + b"Content-Length: 100000\r\n\r\n", b"b" * 100_000, False),
    "silent after reading": (b"", b"", False),
}


class HostileReceiver:
    """Reads each request, then answers as `ANSWERS` says, until the client leaves."""

    def __init__(self, at_once: bytes, trickled: bytes, endless: bool) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.at_once, self.trickled, self.endless = at_once, trickled, endless
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            threading.Thread(target=self._answer, args=(conn,), daemon=True).start()

    def _answer(self, conn: socket.socket) -> None:
        with conn:
            try:
                conn.recv(65536)
                conn.sendall(self.at_once)
                for b in self.trickled:
                    conn.sendall(bytes([b]))
                    time.sleep(0.2)
                while self.endless:
                    conn.sendall(b"z" * 65536)
                time.sleep(60)
            except OSError:
                return

    def close(self) -> None:
        self.server.close()


@pytest.mark.parametrize("answer", ANSWERS)
def test_a_receiver_answering_slowly_or_without_end_costs_one_timeout_a_try(answer) -> None:
    """One worker, a hostile receiver and a healthy one: each try at the hostile one ends
    within the timeout in all (not per socket read), its answer's body is never read into
    memory, and the healthy webhook gets every alert meanwhile."""
    hostile = HostileReceiver(*ANSWERS[answer])
    port = free_port()
    healthy = Receiver(port)
    began = time.monotonic()
    deliveries = started(
        [
            Webhook("hostile", f"http://127.0.0.1:{hostile.port}/", SECRET),
            Webhook("healthy", f"http://127.0.0.1:{port}/", SECRET),
        ],
        dataclasses.replace(POLICY, workers=1),
        alerts=3,
    )
    try:
        wait_for(lambda: deliveries.queued("healthy") == 0, 20)
        wait_for(lambda: deliveries.health()["hostile"].paused_reason, 20)
        took = time.monotonic() - began
        # Three tries of at most the timeout each, the backoffs between them, and slack.
        assert took < POLICY.max_tries * POLICY.timeout_s + 3, took
        health = deliveries.health()["hostile"]
        assert health.delivered == 0 and health.failed_tries == POLICY.max_tries, health
        assert len(healthy.delivered()) == 3
    finally:
        deliveries.close()
        healthy.close()
        hostile.close()
