"""The history's Kafka source against tansu: a member kept alive through a long insert keeps
its partitions and commits; one that is not loses them (the behaviour keep_alive exists for)."""

from __future__ import annotations

import os
import signal
import time

from confluent_kafka import Producer

from mapservice.adapters.kafka_batch_source import KafkaBatchSource, consumer_config
from mapservice.adapters.kafka_topics import ensure_topics
from mapservice.local import embedded
from mapservice.settings import Settings


def first_batch(source: KafkaBatchSource, n: int, timeout_s: float = 60) -> list:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        records = source.poll(n, 0.5)
        if records:
            return records
    raise AssertionError("no records before the deadline")


def test_a_source_kept_alive_past_the_poll_interval_commits_and_skips_nothing(tmp_path) -> None:
    """Past max.poll.interval without a poll, keep_alive keeps the commit valid and the next poll goes on at the next offset; without it the commit fails."""
    port = embedded.free_port()
    settings = Settings(kafka_bootstrap=f"127.0.0.1:{port}", data_dir=tmp_path,
                        topic_pose_events="membership-poses")
    tansu = embedded.start_tansu(port)
    kept = KafkaBatchSource(settings, [settings.topic_pose_events], "membership-kept")
    dropped = KafkaBatchSource(settings, [settings.topic_pose_events], "membership-dropped")
    try:
        ensure_topics(settings)
        producer = Producer(settings.kafka_config())
        for n in range(10):
            producer.produce(settings.topic_pose_events, value=b"%d" % n, partition=0)
        assert producer.flush(30) == 0
        kept.start()
        dropped.start()
        batch_kept, batch_dropped = first_batch(kept, 3), first_batch(dropped, 3)
        poll_interval_s = consumer_config(settings, "g")["max.poll.interval.ms"] / 1000
        until = time.monotonic() + poll_interval_s + 5  # as an insert retried through an outage
        while time.monotonic() < until:
            kept.keep_alive()
            time.sleep(1)
        assert kept.commit(batch_kept), "the kept-alive member lost its group"
        assert not dropped.commit(batch_dropped), "a member past its poll interval should be dropped"
        rest = []
        deadline = time.monotonic() + 30
        while len(rest) < 10 - len(batch_kept) and time.monotonic() < deadline:
            rest += kept.poll(100, 0.5)
        offsets = [r.offset for r in batch_kept + rest if r.partition == 0]
        assert offsets == list(range(10)), offsets
    finally:
        kept.close()
        dropped.close()
        os.killpg(tansu.pid, signal.SIGKILL)
        tansu.wait(10)
