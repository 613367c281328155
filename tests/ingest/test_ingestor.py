"""The broker-free gateway core: route, publish, and ack only once the log has the record."""

from __future__ import annotations

from functools import partial

from mapservice.core.events import MapMetaSet, decode, decode_dead_letter
from mapservice.ingest.gateway import Ingestor
from mapservice.settings import Settings
from mapservice.testing.memory_publisher import MemoryPublisher
from tests.ingest.ingestor_kit import acks, ingestor, publisher, settings  # noqa: F401  (fixtures)


def test_accepted_chunk_is_published_to_chunk_topic(
    ingestor, publisher, settings, wire, acks
) -> None:
    """An accepted chunk lands on the chunk topic with key `row:column`."""
    ingestor.handle("iot/chunks/create", wire.chunk(row=4, column=9), acks.for_("m1"))
    publisher.poll()
    assert list(publisher.records) == [settings.topic_chunk_events]
    ((key, value),) = publisher.records[settings.topic_chunk_events]
    assert key == b"4:9"
    assert decode(value).payload.row == 4


def test_accepted_pose_is_published_to_pose_topic(
    ingestor, publisher, settings, wire, acks, now_ms
) -> None:
    """An accepted pose lands on the pose topic keyed by robot, stamped with the clock's time."""
    ingestor.handle("iot/coordinates/blabla", wire.pose(), acks.for_("m1"))
    publisher.poll()
    ((key, value),) = publisher.records[settings.topic_pose_events]
    assert key == b"blabla"
    assert decode(value).receive_time_ms == now_ms


def test_rejected_message_goes_to_dead_letter_topic(ingestor, publisher, settings, acks) -> None:
    """A rejected message is published as a dead letter (reason, detail, bytes, topic) and acked."""
    ingestor.handle("iot/chunks/create", b"\x00not json", acks.for_("bad"))
    publisher.poll()
    ((key, value),) = publisher.records[settings.topic_dead_letter]
    letter = decode_dead_letter(value)
    assert key == b"iot/chunks/create"
    assert (letter.reason, letter.payload, letter.mqtt_topic, letter.gateway) == (
        "not_json",
        b"\x00not json",
        "iot/chunks/create",
        "gw-test",
    )
    assert letter.detail
    assert acks.calls == ["bad"]


def test_ack_waits_for_delivery(ingestor, publisher, wire, acks) -> None:
    """ack() is not called when handle() returns, only once the publisher delivered (on poll)."""
    ingestor.handle("iot/chunks/create", wire.chunk(), acks.for_("chunk"))
    ingestor.handle("iot/coordinates/blabla", wire.pose(), acks.for_("pose"))
    ingestor.handle("iot/chunks/create", b"garbage", acks.for_("bad"))
    assert acks.calls == []
    assert ingestor.in_flight == 3
    assert not publisher.records
    publisher.poll()
    assert acks.calls == ["chunk", "pose", "bad"]
    assert ingestor.in_flight == 0


def test_failed_delivery_is_retried_and_ack_waits(
    ingestor, publisher, settings, wire, acks
) -> None:
    """A failed delivery is published again; ack waits until a delivery succeeds, once."""
    publisher.fail_with = RuntimeError("broker down")
    ingestor.handle("iot/coordinates/blabla", wire.pose(), acks.for_("pose"))
    publisher.poll()  # fails; the record waits for its retry
    assert ingestor.retries_waiting == 1 and ingestor.retry_due() == 1
    publisher.poll()  # fails again
    assert ingestor.retry_due() == 1
    assert acks.calls == []
    assert ingestor.in_flight == 1
    assert not publisher.records[settings.topic_pose_events]
    publisher.fail_with = None
    publisher.poll()
    assert acks.calls == ["pose"]
    assert ingestor.in_flight == 0
    assert len(publisher.records[settings.topic_pose_events]) == 1
    publisher.poll()
    assert acks.calls == ["pose"]  # acked exactly once


def test_publisher_failing_from_the_start(settings, clock, wire, acks) -> None:
    """MemoryPublisher(fail_with=...) never acks until the failure clears."""
    publisher = MemoryPublisher(fail_with=OSError("no route to broker"))
    ingestor = Ingestor(settings, publisher, clock, "gw", retry_delay_s=0)
    ingestor.handle("iot/chunks/create", wire.chunk(), acks.for_("c"))
    publisher.poll()
    assert acks.calls == []
    publisher.fail_with = None
    assert ingestor.retry_due() == 1
    assert publisher.flush() == 0
    assert acks.calls == ["c"]


def test_a_failed_delivery_waits_its_delay_without_holding_up_other_reports(
    settings, clock, wire, acks
) -> None:
    """A failed record is not produced again inside the delivery callback (which would
    hold up every other report) but by retry_due() once its delay has passed."""
    publisher = MemoryPublisher(fail_with=OSError("request timed out"))
    now = [100.0]
    ingestor = Ingestor(
        settings, publisher, clock, "gw", retry_delay_s=0.2, monotonic=lambda: now[0]
    )
    for n in range(3):
        ingestor.handle("iot/coordinates/blabla", wire.pose(), acks.for_(f"p{n}"))
    publisher.poll()  # three failures, served at once
    assert ingestor.retries_waiting == 3 and ingestor.retry_due() == 0
    now[0] += 0.2
    publisher.fail_with = None
    assert ingestor.retry_due() == 3
    publisher.poll()
    assert acks.calls == ["p0", "p1", "p2"] and ingestor.in_flight == 0


def test_returned_record_describes_the_outcome(ingestor, wire) -> None:
    """handle() returns the routed record: reason None for events, the code for rejections."""
    assert ingestor.handle("iot/chunks/create", wire.chunk(), lambda: None).reason is None
    assert ingestor.handle("iot/nowhere", wire.chunk(), lambda: None).reason == "unknown_topic"


def test_clock_decides_what_is_too_new(ingestor, clock, wire, acks) -> None:
    """The injected clock is the gateway's now: moving it back makes a message 'in the future'."""
    assert ingestor.handle("iot/coordinates/blabla", wire.pose(), lambda: None).reason is None
    clock.advance(-3_600_000)
    record = ingestor.handle("iot/coordinates/blabla", wire.pose(), lambda: None)
    assert record.reason == "timestamp_in_future"


def test_settings_define_the_initial_limits(clock, wire) -> None:
    """Chunk size, grid bound and message size come from the settings until a meta is set."""
    s = Settings(chunk_width=10, chunk_height=10, max_grid=5, max_message_bytes=4096)
    ing = Ingestor(s, MemoryPublisher(), clock, "gw")
    small = wire.chunk(pgmB64compressedData=wire.b64z(bytes(100)), row=4, column=4)
    assert ing.handle("iot/chunks/create", small, lambda: None).reason is None
    assert ing.handle("iot/chunks/create", wire.chunk(), lambda: None).reason == "wrong_chunk_size"
    assert (
        ing.handle(
            "iot/chunks/create",
            wire.chunk(pgmB64compressedData=wire.b64z(bytes(100)), row=5),
            lambda: None,
        ).reason
        == "out_of_map"
    )
    assert ing.handle("iot/chunks/create", b"x" * 5000, lambda: None).reason == "oversized"


def test_apply_meta_narrows_the_grid(ingestor, wire) -> None:
    """After apply_meta, chunks outside the meta's rows/columns are out_of_map."""
    assert (
        ingestor.handle("iot/chunks/create", wire.chunk(row=10, column=10), lambda: None).reason
        is None
    )
    ingestor.apply_meta(
        MapMetaSet(
            width=300, height=200, chunk_width=100, chunk_height=100, chunk_rows=2, chunk_cols=3
        )
    )
    assert (
        ingestor.handle("iot/chunks/create", wire.chunk(row=10, column=10), lambda: None).reason
        == "out_of_map"
    )
    assert (
        ingestor.handle("iot/chunks/create", wire.chunk(row=1, column=2), lambda: None).reason
        is None
    )
    assert (
        ingestor.handle("iot/chunks/create", wire.chunk(row=2, column=0), lambda: None).reason
        == "out_of_map"
    )


def test_apply_meta_sets_chunk_size_and_does_not_compound(ingestor, wire) -> None:
    """apply_meta replaces (not stacks) the previous meta, chunk size included."""
    ingestor.apply_meta(
        MapMetaSet(
            width=100, height=100, chunk_width=50, chunk_height=50, chunk_rows=2, chunk_cols=2
        )
    )
    half = wire.chunk(pgmB64compressedData=wire.b64z(bytes(2500)), row=1, column=1)
    assert ingestor.handle("iot/chunks/create", half, lambda: None).reason is None
    assert (
        ingestor.handle("iot/chunks/create", wire.chunk(row=1, column=1), lambda: None).reason
        == "wrong_chunk_size"
    )
    ingestor.apply_meta(
        MapMetaSet(
            width=800, height=800, chunk_width=100, chunk_height=100, chunk_rows=8, chunk_cols=8
        )
    )
    assert (
        ingestor.handle("iot/chunks/create", wire.chunk(row=7, column=7), lambda: None).reason
        is None
    )
    assert ingestor.limits.max_message_bytes == Settings().max_message_bytes


def test_a_handled_and_delivered_message_leaves_nothing_for_the_cyclic_collector(
    ingestor, publisher, wire
) -> None:
    """Routing, publishing, a failed delivery's retry and the ack free every object by
    reference counting: a cycle per message made gc ~12 % of the gateway's CPU.

    The collector counts every unreachable object of the process, also what a thread left
    by an earlier test drops meanwhile; the ingestor's cycles would come back in every
    round (200 messages with a cycle each left ~2,000), such noise does not: the quietest
    of three rounds is asserted."""
    import gc

    # The youngest generation only: with the collector disabled every object made in the
    # round stays in it, so its cycles are all found there, without a pass over the whole
    # heap of a test worker that has run thousands of tests (seconds per full collection).
    def one_round(first_mid: int) -> int:
        acked = []
        gc.collect(0)
        gc.disable()
        try:
            publisher.fail_with = RuntimeError("broker down")
            for mid in range(first_mid, first_mid + 200):
                ingestor.handle("iot/coordinates/blabla", wire.pose(), partial(acked.append, mid))
            publisher.poll()  # every delivery fails: each record waits for its retry
            publisher.fail_with = None
            assert ingestor.retry_due() == 200
            publisher.poll()
            assert len(acked) == 200 and ingestor.in_flight == 0
            return gc.collect(0)
        finally:
            gc.enable()

    counts = [one_round(1000 * r) for r in range(3)]
    assert min(counts) < 10, counts


def test_new_robot_ids_beyond_the_limit_are_dead_lettered(publisher, clock, wire, acks) -> None:
    """Open mode: three new robot ids a minute pass, a fourth new one is a dead letter
    `too_many_new_robots` whose detail names the setting, and robots already seen still pass."""
    ingestor = Ingestor(
        Settings(ingest_new_robots_limit="3/minute"), publisher, clock, "gw", retry_delay_s=0
    )
    for robot in ("a", "b", "c", "d", "a"):
        ingestor.handle(f"iot/coordinates/{robot}", wire.pose(robotId=robot), acks.for_(robot))
    publisher.poll()
    settings = Settings()
    stored = [decode(v).robot_id for _, v in publisher.records[settings.topic_pose_events]]
    assert stored == ["a", "b", "c", "a"]
    ((_, value),) = publisher.records[settings.topic_dead_letter]
    letter = decode_dead_letter(value)
    assert letter.reason == "too_many_new_robots" and "'d'" in letter.detail
    assert "MAPSERVICE_INGEST_NEW_ROBOTS_LIMIT" in letter.detail
    assert acks.calls == ["a", "b", "c", "d", "a"]  # the refused one is acknowledged too


def test_no_new_robot_limit_when_empty(publisher, clock, wire, acks) -> None:
    ingestor = Ingestor(
        Settings(ingest_new_robots_limit=""), publisher, clock, "gw", retry_delay_s=0
    )
    for n in range(50):
        ingestor.handle(f"iot/coordinates/r{n}", wire.pose(robotId=f"r{n}"), acks.for_("x"))
    publisher.poll()
    assert len(publisher.records[Settings().topic_pose_events]) == 50
