"""`mapservice bench group-protocol`: how long the history consumer's group takes to give a
lost member's partitions to the member that survives, with the classic consumer group
protocol and with Kafka 4's consumer protocol (KIP-848, `group.protocol=consumer`).

On one embedded Apache Kafka node (as `mapservice up` runs it, kafka_broker.py): a topic
of six partitions written to all the time, two members of one group with the history
consumer's configuration (adapters/kafka_batch_source.consumer_config): the survivor in
this process, the other in a child process. Once each holds three partitions, the child is
killed (SIGKILL: no leave-group, as a crashed or OOM-killed `serve`), and the time is taken
until the survivor has read a record written after the kill from each of the lost
partitions. Also taken: how long the join of the second member takes (the survivor's
partitions moving to it). Rounds alternate the protocols; medians are reported.
"""

from __future__ import annotations

import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

PROTOCOLS = ("classic", "consumer")
PARTITIONS = 6


def member_config(bootstrap: str, group: str, protocol: str) -> dict:
    """The history consumer's librdkafka configuration with `protocol`."""
    from mapservice.adapters.kafka_batch_source import consumer_config
    from mapservice.settings import Settings

    settings = Settings(kafka_bootstrap=bootstrap, kafka_group_protocol=protocol)
    return {**consumer_config(settings, group), "statistics.interval.ms": 0, "log_level": 3}


class Producer(threading.Thread):
    """Writes a record to every partition every `every_s`, its value the wall time."""

    def __init__(self, bootstrap: str, topic: str, every_s: float = 0.05) -> None:
        super().__init__(name="group-protocol-producer", daemon=True)
        from confluent_kafka import Producer as KafkaProducer

        self.producer = KafkaProducer({"bootstrap.servers": bootstrap, "linger.ms": 5})
        self.topic, self.every_s = topic, every_s
        self.stopping = threading.Event()

    def run(self) -> None:
        while not self.stopping.wait(self.every_s):
            now = f"{time.time():.6f}".encode()
            for p in range(PARTITIONS):
                self.producer.produce(self.topic, now, partition=p)
            self.producer.poll(0)
        self.producer.flush(10)


class Survivor(threading.Thread):
    """A member in this process: its current assignment, and per partition the write time
    of the newest record it read."""

    def __init__(self, config: dict, topic: str) -> None:
        super().__init__(name="group-protocol-survivor", daemon=True)
        from confluent_kafka import Consumer

        self.consumer = Consumer(config)
        self.topic = topic
        self.assignment: set[int] = set()
        self.newest_written: dict[int, float] = {}
        self.stopping = threading.Event()
        self.lock = threading.Lock()

    def run(self) -> None:
        self.consumer.subscribe([self.topic])
        try:
            while not self.stopping.is_set():
                for msg in self.consumer.consume(500, timeout=0.1):
                    partition, value = msg.partition(), msg.value()
                    if msg.error() is None and partition is not None and value is not None:
                        with self.lock:
                            self.newest_written[partition] = max(
                                self.newest_written.get(partition, 0.0), float(value)
                            )
                with self.lock:
                    self.assignment = {tp.partition for tp in self.consumer.assignment()}
        finally:
            self.consumer.close()

    def holds(self) -> set[int]:
        with self.lock:
            return set(self.assignment)

    def read_since(self, partitions: set[int], since: float) -> bool:
        """Whether it read a record written after `since` from each of `partitions`."""
        with self.lock:
            return all(self.newest_written.get(p, 0.0) > since for p in partitions)


def wait_until(condition, timeout_s: float, what: str, poll_s: float = 0.02) -> float:
    """Seconds until `condition()` held; raises after `timeout_s`, naming `what`."""
    t0 = time.monotonic()
    while not condition():
        if time.monotonic() - t0 > timeout_s:
            raise TimeoutError(f"{what} did not happen within {timeout_s:.0f} s")
        time.sleep(poll_s)
    return time.monotonic() - t0


def create_topic(bootstrap: str, topic: str) -> None:
    from confluent_kafka.admin import AdminClient, NewTopic

    admin = AdminClient({"bootstrap.servers": bootstrap})
    admin.create_topics([NewTopic(topic, PARTITIONS, 1)])[topic].result(30)


def member_loss(bootstrap: str, protocol: str, timeout_s: float = 90.0) -> dict:
    """One round: the second member's join, then its SIGKILL; seconds for each."""
    from mapservice.local.embedded import module_command

    topic = f"bench-group-protocol-{uuid.uuid4().hex[:8]}"
    group = f"{topic}-group"
    create_topic(bootstrap, topic)
    config = member_config(bootstrap, group, protocol)
    producer = Producer(bootstrap, topic)
    survivor = Survivor(config, topic)
    child = None
    try:
        producer.start()
        survivor.start()
        wait_until(
            lambda: len(survivor.holds()) == PARTITIONS, timeout_s, "the first member's assignment"
        )
        joined_at = time.monotonic()
        child = subprocess.Popen(
            module_command(
                "mapservice.bench.group_protocol",
                "member",
                # The logger is an object, not a setting: the child adds its own.
                json.dumps({k: v for k, v in config.items() if k != "logger"}),
                topic,
            ),
            stdout=subprocess.PIPE,
            text=True,
        )
        wait_until(
            lambda: len(survivor.holds()) == PARTITIONS // 2,
            timeout_s,
            "the partitions' move to the second member",
        )
        join_s = time.monotonic() - joined_at
        assert child.stdout is not None
        # The child says when it reads from its partitions (then it truly holds them).
        line = child.stdout.readline()
        if not line.startswith("reading"):
            raise RuntimeError(f"the second member did not start reading: {line!r}")
        time.sleep(2)  # steady: both members fetching
        lost = set(range(PARTITIONS)) - survivor.holds()
        killed_at_wall, killed_at = time.time(), time.monotonic()
        os.kill(child.pid, signal.SIGKILL)
        child.wait()
        reassigned_s = wait_until(
            lambda: lost <= survivor.holds(),
            timeout_s,
            "the lost member's partitions' move to the survivor",
        )
        wait_until(
            lambda: survivor.read_since(lost, killed_at_wall),
            timeout_s,
            "reading the lost partitions' new records",
        )
        return {
            "protocol": protocol,
            "join_s": join_s,
            "reassigned_s": reassigned_s,
            "recovered_s": time.monotonic() - killed_at,
        }
    finally:
        if child is not None and child.poll() is None:
            child.kill()
            child.wait()
        survivor.stopping.set()
        producer.stopping.set()
        survivor.join(15)
        producer.join(15)


def _member(config_json: str, topic: str) -> None:
    """The child member: reads until killed; says once when it reads records."""
    from confluent_kafka import Consumer

    from mapservice.adapters.kafka_logs import logged

    consumer = Consumer(logged(json.loads(config_json)))
    consumer.subscribe([topic])
    said = False
    while True:
        msgs = consumer.consume(500, timeout=0.1)
        if not said and any(m.error() is None for m in msgs):
            print("reading", flush=True)
            said = True


def run(rounds: int, console, work_dir: Path) -> dict:
    from mapservice.local import kafka_broker
    from mapservice.local.embedded import free_port

    node = kafka_broker.KafkaNodeConfig(
        log_dir=work_dir / "kafka" / "log", port=free_port(), controller_port=free_port()
    )
    with open(work_dir / "kafka.log", "wb") as log_file:
        broker = kafka_broker.start_kafka(node, log_file)
        results: list[dict] = []
        try:
            for i in range(rounds):
                order = PROTOCOLS if i % 2 == 0 else tuple(reversed(PROTOCOLS))
                for protocol in order:
                    r = member_loss(f"127.0.0.1:{node.port}", protocol)
                    r["round"] = i + 1
                    results.append(r)
                    console.print(
                        f"round {i + 1} {protocol:8s}: join {r['join_s']:.2f} s, lost member's "
                        f"partitions reassigned after {r['reassigned_s']:.2f} s, read again "
                        f"after {r['recovered_s']:.2f} s (load {os.getloadavg()[0]:.2f})"
                    )
        finally:
            kafka_broker.stop_process_group(broker)
    medians = {
        p: {
            k: statistics.median(r[k] for r in results if r["protocol"] == p)
            for k in ("join_s", "reassigned_s", "recovered_s")
        }
        for p in PROTOCOLS
    }
    return {
        "kafka": kafka_broker.kafka_version(),
        "partitions": PARTITIONS,
        "session_timeout_ms": 10_000,
        "heartbeat_interval_ms": 1000,
        "rounds": results,
        "medians": medians,
    }


def main(args) -> None:
    from rich.console import Console

    from mapservice.bench.machine import machine_facts

    console = Console()
    if args.rounds < 1:
        sys.exit("--rounds must be at least 1")
    facts = machine_facts()
    with tempfile.TemporaryDirectory(prefix="bench-group-protocol-") as tmp:
        result = run(args.rounds, console, Path(tmp))
    facts["loadavg_at_end"] = os.getloadavg()
    result["machine"] = facts
    for p, m in result["medians"].items():
        console.print(
            f"{p:8s} (median of {args.rounds}): join {m['join_s']:.2f} s, member lost -> "
            f"partitions reassigned {m['reassigned_s']:.2f} s, read again {m['recovered_s']:.2f} s"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2, default=str))
        console.print(f"wrote {args.json}")


def add_parser(kinds) -> None:
    bench = kinds.add_parser(
        "group-protocol",
        help="the history consumer's group on the embedded "
        "Apache Kafka: a member's join and its loss (SIGKILL) with the classic "
        "and the consumer (KIP-848) group protocol",
    )
    bench.add_argument(
        "--rounds",
        type=int,
        default=3,
        help="rounds, each one loss per protocol "
        "(alternating which goes first); medians are reported",
    )
    bench.add_argument(
        "--json", default=None, help="write the rounds and medians as JSON to this file"
    )
    bench.set_defaults(func=main)


if __name__ == "__main__":
    # The child member of `member_loss`.
    if sys.argv[1:2] == ["member"]:
        _member(sys.argv[2], sys.argv[3])
    else:
        sys.exit("usage: python -m mapservice.bench.group_protocol member CONFIG_JSON TOPIC")
