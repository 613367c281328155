"""One contract for every EventSource: the memory twin (mapservice/testing/memory_source.py)
and KafkaBatchSource on Apache Kafka (the session's embedded node; those cases are
integration tests). A kit per adapter writes records to a one-partition topic, opens
members of one consumer group, and changes the group under a member.

The rule the twin must share with Kafka: nothing counts as consumed until committed, and
a member whose group changed after it was handed records cannot commit them (its commit
says False), so they are delivered again.
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Iterator, Sequence

import pytest

from mapservice.core.ports import EventSource, SourceRecord
from mapservice.testing.memory_source import MemorySource

TOPIC = "contract-events"
WAIT_S = 60.0  # generous: a Kafka group's join, not a measurement


class MemoryKit:
    """The twin: one MemorySource is the group's only member and its log."""

    def __init__(self) -> None:
        self.source = MemorySource()
        self.topic = TOPIC
        self.poll_interval_s = 0.0  # the twin never drops a member that does not poll

    def produce(self, values: Sequence[bytes]) -> None:
        for v in values:
            self.source.append(self.topic, v)

    def member(self) -> EventSource:
        self.source.start()
        return self.source

    def restart(self, member: EventSource) -> EventSource:
        self.source.restart()
        return self.source

    def change_group(self, member: EventSource) -> tuple[list[EventSource], list[SourceRecord]]:
        self.source.rebalance()
        return [self.source], []

    def change_group_while_staying(self, member: EventSource) -> EventSource:
        self.source.rebalance()
        member.stay_in_group()
        return self.source

    def leave(self, other: EventSource) -> None:
        """The twin's group has one member: nothing leaves."""

    def close(self) -> None:
        self.source.close()


class KafkaKit:
    """KafkaBatchSource members of a new group on a new one-partition topic."""

    def __init__(self, bootstrap: str) -> None:
        from confluent_kafka import Producer
        from confluent_kafka.admin import AdminClient, NewTopic

        from mapservice.adapters.kafka_batch_source import consumer_config
        from mapservice.settings import Settings

        self.topic = f"contract-{uuid.uuid4().hex[:8]}"
        self.group = f"{self.topic}-group"
        admin = AdminClient({"bootstrap.servers": bootstrap})  # held until the topic exists
        admin.create_topics([NewTopic(self.topic, 1, 1)])[self.topic].result(30)
        self.settings = Settings(kafka_bootstrap=bootstrap)
        config = consumer_config(self.settings, self.group)
        self.poll_interval_s = config["max.poll.interval.ms"] / 1000
        self.producer = Producer({"bootstrap.servers": bootstrap})
        self.members: list = []
        self.assignments: dict[int, int] = {}  # id(member) -> assignments seen

    def produce(self, values: Sequence[bytes]) -> None:
        for v in values:
            self.producer.produce(self.topic, v, partition=0)
        assert self.producer.flush(30) == 0

    def member(self) -> EventSource:
        from mapservice.adapters.kafka_batch_source import KafkaBatchSource

        holder: list = []
        source = KafkaBatchSource(
            self.settings,
            [self.topic],
            self.group,
            on_assigned=lambda _parts: self._assigned(holder[0]),
        )
        holder.append(source)
        self.assignments[id(source)] = 0
        source.start()
        self.members.append(source)
        return source

    def _assigned(self, source) -> None:
        self.assignments[id(source)] += 1

    def restart(self, member: EventSource) -> EventSource:
        self._settle(member)
        member.close()
        self.members.remove(member)
        return self.member()

    def _settle(self, member: EventSource) -> None:
        """Lets librdkafka finish a commit (sent asynchronously) before the member goes:
        its answer arrives inside a poll."""
        assert member.poll(100, 1.0) == []

    def change_group(self, member: EventSource) -> tuple[list[EventSource], list[SourceRecord]]:
        """A second member joins; polls both until each has been assigned since. Returns
        the members and whatever they were handed meanwhile."""
        before = self.assignments[id(member)]
        other = self.member()
        delivered: list[SourceRecord] = []
        deadline = time.monotonic() + WAIT_S
        while not (self.assignments[id(member)] > before and self.assignments[id(other)] > 0):
            assert time.monotonic() < deadline, "the group did not rebalance"
            delivered += member.poll(100, 0.2) + other.poll(100, 0.2)
        return [member, other], delivered

    def change_group_while_staying(self, member: EventSource) -> EventSource:
        """A second member joins while `member` only stays in its group (long work: an
        insert retried through an outage), until both were assigned since: the partition
        is taken from `member` inside `stay_in_group`. Returns the other member."""
        before = self.assignments[id(member)]
        other = self.member()
        deadline = time.monotonic() + WAIT_S
        while not (self.assignments[id(member)] > before and self.assignments[id(other)] > 0):
            assert time.monotonic() < deadline, "the group did not rebalance"
            member.stay_in_group()
            assert other.poll(100, 0.2) == []  # everything written was handed out before
        return other

    def leave(self, other: EventSource) -> None:
        """`other` leaves the group: the rest take its partitions at their next polls."""
        other.close()
        self.members.remove(other)

    def close(self) -> None:
        for m in self.members:
            m.close()
        self.producer = None  # librdkafka's handle goes now, not at exit after the broker


@pytest.fixture(
    params=[
        "memory",
        pytest.param("kafka", marks=[pytest.mark.integration, pytest.mark.timeout(180)]),
    ]
)
def kit(request) -> Iterator[MemoryKit | KafkaKit]:
    made = (
        MemoryKit()
        if request.param == "memory"
        else KafkaKit(request.getfixturevalue("apache_kafka"))
    )
    yield made
    made.close()


def poll_until(members: Sequence[EventSource], count: int) -> list[SourceRecord]:
    """Polls the members until they were handed `count` records between them."""
    got: list[SourceRecord] = []
    deadline = time.monotonic() + WAIT_S
    while len(got) < count:
        assert time.monotonic() < deadline, f"only {len(got)} of {count} records delivered"
        for m in members:
            got += m.poll(count, 0.2)
    return got


def values(records: Sequence[SourceRecord]) -> list[bytes]:
    return [r.value for r in records]


def test_records_come_in_offset_order_with_their_place_in_the_log(kit) -> None:
    kit.produce([b"a", b"b", b"c"])
    member = kit.member()
    got = poll_until([member], 3)
    assert values(got) == [b"a", b"b", b"c"]
    assert [(r.topic, r.partition, r.offset) for r in got] == [(kit.topic, 0, o) for o in range(3)]


def test_what_is_not_committed_is_delivered_again_to_the_next_member(kit) -> None:
    kit.produce([b"a", b"b"])
    member = kit.member()
    poll_until([member], 2)
    again = kit.restart(member)
    assert values(poll_until([again], 2)) == [b"a", b"b"]


def test_a_new_member_resumes_after_the_committed_records(kit) -> None:
    # The batch that carries a member's first assignment is never committed (Kafka may
    # hand out records fetched on either side of the rebalance in it): commit later ones.
    member = kit.member()
    kit.produce([b"a"])
    poll_until([member], 1)
    kit.produce([b"b", b"c"])
    got = poll_until([member], 2)
    assert values(got) == [b"b", b"c"]
    assert member.commit(got[:1]) is True
    again = kit.restart(member)
    kit.produce([b"d"])
    assert values(poll_until([again], 2)) == [b"c", b"d"]


def test_records_handed_out_before_the_group_changed_are_not_committed(kit) -> None:
    """The group-membership rule: the member's commit of records it was handed before the
    group changed says False, and the records are delivered again (to whichever member
    now owns the partition)."""
    kit.produce([b"a", b"b", b"c"])
    member = kit.member()
    got = poll_until([member], 3)
    members, meanwhile = kit.change_group(member)
    assert member.commit(got) is False
    redelivered = meanwhile + poll_until(members, max(0, 3 - len(meanwhile)))
    assert sorted(set(values(redelivered))) == [b"a", b"b", b"c"]


def test_records_handed_out_after_the_group_changed_are_committed(kit) -> None:
    """The rule refuses only the past membership's records: what the partition's owner is
    handed once the group has settled commits."""
    kit.produce([b"a"])
    member = kit.member()
    poll_until([member], 1)
    members, _ = kit.change_group(member)
    kit.produce([b"b"])
    handed: dict[int, list[SourceRecord]] = {id(m): [] for m in members}
    deadline = time.monotonic() + WAIT_S
    while not any(b"b" in values(batch) for batch in handed.values()):
        assert time.monotonic() < deadline, "the record written after the change never came"
        for m in members:
            handed[id(m)] += m.poll(10, 0.2)
    owner = next(m for m in members if b"b" in values(handed[id(m)]))
    settled = [r for r in handed[id(owner)] if r.value == b"b"]
    assert owner.commit(settled) is True


def test_a_member_that_stays_in_its_group_through_long_work_commits_what_it_was_handed(
    kit,
) -> None:
    """Work between polls longer than the group's poll interval (a rebuild, an insert
    retried through an outage), with `stay_in_group` every second: the member keeps its
    membership (its commit of what it was handed before says True) and is handed nothing
    meanwhile; what was written during the work comes with the next poll, once, in order."""
    member = kit.member()
    kit.produce([b"a"])
    poll_until([member], 1)  # the first assignment's batch, never committed
    kit.produce([b"b"])
    got = poll_until([member], 1)
    assert values(got) == [b"b"]
    kit.produce([b"c", b"d"])
    until = time.monotonic() + kit.poll_interval_s + 3
    while time.monotonic() < until:
        member.stay_in_group()
        time.sleep(1.0 if kit.poll_interval_s else 0)
    member.stay_in_group()
    assert member.commit(got) is True
    assert values(poll_until([member], 2)) == [b"c", b"d"]
    kit.produce([b"e"])
    assert values(poll_until([member], 1)) == [b"e"]


def test_a_member_whose_group_changed_while_it_stayed_in_it_is_handed_what_comes_next(
    kit,
) -> None:
    """The group changes while a member only stays in it (`stay_in_group` pauses its
    partitions for the call), and later hands the partition back to it: what is written
    then reaches it. A partition paused at the revocation stayed paused through its next
    assignment, and the history stopped for good after a Kafka outage during a ClickHouse one."""
    member = kit.member()
    kit.produce([b"a"])
    poll_until([member], 1)
    other = kit.change_group_while_staying(member)
    kit.leave(other)
    kit.produce([b"b"])
    got: list[SourceRecord] = []  # "a" again first: it was never committed
    deadline = time.monotonic() + WAIT_S
    while b"b" not in values(got):
        assert time.monotonic() < deadline, (
            f"only {values(got)} handed out: the partition stayed paused"
        )
        got += member.poll(10, 0.2)
    assert set(values(got)) == {b"a", b"b"}
