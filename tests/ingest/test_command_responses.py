"""The gateway's command half: the relay delivers each fresh command on its robot's own
topic (and remembers which robot it went to; a stale one is not delivered), and the
robots' acks and outcomes become events on the command topic, or dead letters with their
reason: malformed, about another robot, about a command that robot was never sent.
A fuzzer sends 2,000 generated answers: each ends as an event or a dead letter."""

from __future__ import annotations

import json

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mapservice.core.commands import CommandAcknowledged, CommandFinished
from mapservice.core.events import decode, decode_dead_letter, encode, make_envelope
from mapservice.core.wire2019 import Reason, format_timestamp
from tests.ingest import gateway_kit
from tests.ingest.fuzz_kit import FuzzedGateway, budget, mutate, raw_nasties
from tests.ingest.gateway_kit import NOW


class Gateway(gateway_kit.Gateway):
    def answer(self, robot: str, doc: dict | bytes, topic_robot: str | None = None):
        """A 2019 robot's answer on its command-events topic (`topic_robot`: another robot's)."""
        payload = doc if isinstance(doc, bytes) else json.dumps(doc).encode()
        return self.ingestor.handle(
            f"iot/robots/{topic_robot or robot}/command-events", payload, lambda: None
        )


def ack(robot: str, cid: str, **extra) -> dict:
    return {
        "robotId": robot,
        "commandId": cid,
        "type": "ack",
        "status": "accepted",
        "timestamp": format_timestamp(NOW + 100),
        **extra,
    }


@pytest.fixture
def gw() -> Gateway:
    return Gateway()


def test_a_fresh_command_goes_to_its_robots_topic_a_stale_one_does_not(gw) -> None:
    assert gw.issue("c-1", "agv-1")
    ((topic, payload),) = gw.sent
    assert topic == "iot/robots/agv-1/commands"
    assert payload == {
        "commandId": "c-1",
        "robotId": "agv-1",
        "kind": "pause",
        "issuedBy": "operator:ab12",
        "issuedAt": NOW,
    }
    assert not gw.issue("c-old", "agv-1", at_ms=NOW - 31_000)  # older than the delivery TTL (30 s)
    assert len(gw.sent) == 1
    assert gw.ingestor.router.commands.robot_of("c-old") == "agv-1"  # still known for answers
    answer = encode(
        make_envelope("agv-1", NOW, NOW, CommandAcknowledged("c-1", "agv-1", "accepted"))
    )
    assert not gw.relay.handle(answer) and not gw.relay.handle(b"\x00garbage")


def test_answers_become_events_on_the_command_topic(gw) -> None:
    gw.issue("c-1", "agv-1")
    record = gw.answer("agv-1", ack("agv-1", "c-1"))
    assert record.reason is None and record.topic == gw.settings.topic_command_events
    event = decode(record.value)
    assert event.payload == CommandAcknowledged("c-1", "agv-1", "accepted")
    assert event.event_time_ms == NOW + 100 and event.robot_id == "agv-1"
    record = gw.answer(
        "agv-1",
        {**ack("agv-1", "c-1"), "type": "outcome", "outcome": "failed", "reason": "blocked"},
    )
    assert decode(record.value).payload == CommandFinished("c-1", "agv-1", "failed", "blocked")
    # A redelivery of the same answer is the same event (its id is its identity).
    assert decode(gw.answer("agv-1", ack("agv-1", "c-1")).value).event_id == event.event_id


@pytest.mark.parametrize(
    "doc,topic_robot,reason,says",
    [
        (ack("agv-2", "c-1"), None, Reason.NOT_ITS_COMMAND, "another robot"),
        (ack("agv-1", "c-nobody-sent"), None, Reason.UNKNOWN_COMMAND, "no command"),
        (ack("agv-1", "c-1"), "agv-2", Reason.ROBOT_ID_MISMATCH, "payload says"),
        (
            ack("agv-1", "c-1", status="maybe"),
            None,
            Reason.BAD_COMMAND_RESPONSE,
            "accepted, rejected",
        ),
        (
            {**ack("agv-1", "c-1"), "type": "outcome", "outcome": "exploded"},
            None,
            Reason.BAD_COMMAND_RESPONSE,
            "done, failed, cancelled",
        ),
        (ack("agv-1", "c-1", type="nack"), None, Reason.BAD_COMMAND_RESPONSE, "'ack' or 'outcome'"),
        ({"robotId": "agv-1", "type": "ack"}, None, Reason.MISSING_FIELD, "commandId"),
        (ack("agv-1", "c-1", status=7), None, Reason.WRONG_TYPE, "status"),
        (ack("agv-1", "c-1", timestamp="yesterday"), None, Reason.BAD_TIMESTAMP, "ISO 8601"),
        (
            ack("agv-1", "c-1", timestamp=format_timestamp(NOW + 3_600_000)),
            None,
            Reason.TIMESTAMP_IN_FUTURE,
            "clock",
        ),
        (ack("agv-1", "c 1/#"), None, Reason.WRONG_TYPE, "not a command id"),
        (ack("agv-1", "c-1", reason="x" * 501), None, Reason.OUT_OF_RANGE, "at most 500"),
        (b"{not json", None, Reason.NOT_JSON, "not JSON"),
    ],
)
def test_bad_answers_are_dead_letters_that_say_why(gw, doc, topic_robot, reason, says) -> None:
    gw.issue("c-1", "agv-1")  # sent to agv-1 only
    robot = doc["robotId"] if isinstance(doc, dict) and "robotId" in doc else "agv-1"
    record = gw.answer(robot, doc, topic_robot)
    assert record.reason == reason.value and record.topic == gw.settings.topic_dead_letter
    letter = decode_dead_letter(record.value)
    assert says in letter.detail, letter.detail
    assert letter.mqtt_topic.endswith("/command-events")


def test_a_topic_deeper_or_shallower_than_a_robots_is_no_answer(gw) -> None:
    for topic in (
        "iot/robots/agv-1/command-events/x",
        "iot/robots//command-events",
        "iot/robots/agv-1/commands",
    ):
        record = gw.ingestor.handle(topic, json.dumps(ack("agv-1", "c-1")).encode(), lambda: None)
        assert record.reason == Reason.UNKNOWN_TOPIC.value, topic


FUZZ = budget(2_000)


@st.composite
def answer_payloads(draw) -> bytes:
    good = {
        **ack("fuzz-1", "c-1"),
        **draw(
            st.sampled_from(
                [
                    {},
                    {"type": "outcome", "outcome": "done"},
                    {"status": "rejected", "reason": "busy"},
                ]
            )
        ),
    }
    if draw(st.booleans()):
        return json.dumps(mutate(good, draw)).encode()
    return draw(raw_nasties(good))


@pytest.fixture(scope="module")
def fuzzed_gateway() -> FuzzedGateway:
    """One gateway for every generated answer, with command c-1 sent to fuzz-1."""
    gw = Gateway()
    gw.issue("c-1", "fuzz-1")
    return FuzzedGateway(wired=(gw.settings, gw.ingestor, gw.publisher))


@pytest.mark.usefixtures("quiet_rejection_logs")
@FUZZ
@given(payload=answer_payloads())
def test_generated_answers_end_as_events_or_dead_letters(fuzzed_gateway, payload) -> None:
    event = fuzzed_gateway.fate("iot/robots/fuzz-1/command-events", payload).event
    if event is not None:
        assert event.robot_id == "fuzz-1" and event.payload.command_id == "c-1"
        assert isinstance(event.payload, (CommandAcknowledged, CommandFinished))


def test_the_relays_book_forgets_the_oldest_beyond_its_limit() -> None:
    from mapservice.ingest.command_relay import CommandBook

    book = CommandBook(limit=2)
    for cid in ("a", "b", "c"):
        book.remember(cid, "r")
    assert book.robot_of("a") is None and book.robot_of("c") == "r"


def test_the_relay_reads_again_after_a_failure(gw, monkeypatch) -> None:
    """Kafka away when the relay starts (or any failure while reading): it logs, waits and
    reads again; deliveries never just stop."""
    import mapservice.ingest.command_relay as relay_module

    calls = []

    def read() -> None:
        calls.append(1)
        if len(calls) < 3:
            raise OSError("Kafka unreachable")
        gw.relay._stop.set()

    monkeypatch.setattr(relay_module, "RETRY_S", 0.01)
    monkeypatch.setattr(gw.relay, "_read", read)
    gw.relay._run()
    assert len(calls) == 3 and gw.relay.failures == 2
