"""The embedded Apache Kafka: its jars fetched once (clear errors without Maven or Maven
Central), one KRaft node formatted once whose log survives a SIGKILL, retention and heap
in force, and tansu only as the fallback where no Java is found (said with its cost)."""

from __future__ import annotations

import dataclasses
import os
import signal
import stat
import time
from pathlib import Path

import pytest
from confluent_kafka import OFFSET_BEGINNING, Consumer, Producer, TopicPartition
from confluent_kafka.admin import AdminClient, ConfigResource, NewTopic
from rich.console import Console

from mapservice.local import embedded, kafka_broker
from mapservice.local.stack import Stack
from mapservice.local.up import embedded_kafka_intro, kafka_keeps
from mapservice.settings import Settings


def fake_mvn(tmp_path: Path, script: str) -> Path:
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    mvn = bin_dir / "mvn"
    mvn.write_text("#!/bin/sh\n" + script)
    mvn.chmod(mvn.stat().st_mode | stat.S_IXUSR)
    return bin_dir


def test_the_pom_pins_a_kafka_4_version() -> None:
    """The pom names kafka_2.13 at the pinned version (Kafka 4: KRaft only, Java 17)."""
    version = kafka_broker.kafka_version()
    assert version.split(".")[0] == "4"
    assert "<artifactId>kafka_2.13</artifactId>" in kafka_broker.POM.read_text()


def test_without_maven_the_error_says_how_to_install_it_or_use_tansu(tmp_path, monkeypatch) -> None:
    """No `mvn` on PATH: a RuntimeError naming the Debian package and the tansu fallback."""
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(
        RuntimeError, match=r"apt-get install maven.*MAPSERVICE_EMBEDDED_KAFKA=tansu"
    ):
        kafka_broker.ensure_jars(tmp_path / "jars")


def test_an_unreachable_maven_central_is_a_clear_error(tmp_path, monkeypatch) -> None:
    """Maven failing to resolve: the error names Maven Central, the fallback and Maven's own
    [ERROR] lines, and leaves no half-filled cache behind."""
    bin_dir = fake_mvn(
        tmp_path,
        'echo "[ERROR] Failed to execute goal: Could not transfer '
        'artifact org.apache.kafka:kafka_2.13: Connection refused"\nexit 1\n',
    )
    monkeypatch.setenv("PATH", f"{bin_dir}:{os.environ['PATH']}")
    with pytest.raises(RuntimeError, match="Maven Central") as caught:
        kafka_broker.ensure_jars(tmp_path / "jars")
    assert "Connection refused" in str(caught.value)
    assert "MAPSERVICE_EMBEDDED_KAFKA=tansu" in str(caught.value)
    assert not (tmp_path / "jars" / ".complete").exists()


def test_jars_are_fetched_once_with_progress(tmp_path, monkeypatch) -> None:
    """The first call runs Maven (its downloads reported as progress); later calls use the cache."""
    calls = tmp_path / "calls"
    bin_dir = fake_mvn(
        tmp_path,
        f'echo run >> {calls}\nfor a in "$@"; do case "$a" in '
        '-DoutputDirectory=*) d="${a#-DoutputDirectory=}";; esac; done\n'
        'mkdir -p "$d" && touch "$d/kafka_2.13.jar"\n'
        # As Maven 3.8 prints them in batch mode (-B).
        'echo "[INFO] Downloaded from central: https://repo/kafka_2.13.pom (2 kB)"\n'
        'echo "[INFO] Downloaded from central: https://repo/kafka_2.13.jar (7 MB)"\n',
    )
    monkeypatch.setenv("PATH", f"{bin_dir}:{os.environ['PATH']}")
    seen: list[str] = []
    libs = kafka_broker.ensure_jars(tmp_path / "jars", progress=seen.append)
    assert (libs / "kafka_2.13.jar").exists()
    assert seen == ["Downloaded from central: https://repo/kafka_2.13.jar (7 MB)"]
    assert kafka_broker.ensure_jars(tmp_path / "jars") == libs
    assert calls.read_text().count("run") == 1


def test_the_node_keeps_by_time_and_size_with_a_bounded_heap(tmp_path) -> None:
    """The server properties carry the retention settings, segments a sixteenth of it, one
    static voter on the controller port, and listeners on 127.0.0.1 only."""
    node = kafka_broker.KafkaNodeConfig(
        log_dir=tmp_path / "log",
        port=1234,
        controller_port=1235,
        retention_hours=5,
        retention_bytes=64 * 1024**2,
    )
    props = dict(line.split("=", 1) for line in node.properties().splitlines() if line)
    assert props["log.retention.hours"] == "5"
    assert props["log.retention.bytes"] == str(64 * 1024**2)
    assert props["log.segment.bytes"] == str(4 * 1024**2)
    assert props["controller.quorum.voters"] == "1@127.0.0.1:1235"
    assert props["listeners"] == "PLAINTEXT://127.0.0.1:1234,CONTROLLER://127.0.0.1:1235"
    assert props["log.dirs"] == str(tmp_path / "log")
    # The shortest session MAPSERVICE_KAFKA_SESSION_TIMEOUT_S allows is accepted.
    assert int(props["group.min.session.timeout.ms"]) <= 3000


def test_auto_is_tansu_only_where_no_java_is_found(monkeypatch, tmp_path) -> None:
    """MAPSERVICE_EMBEDDED_KAFKA=auto: apache with Java, tansu without; the stack follows."""
    monkeypatch.delenv("JAVA_HOME", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path))
    assert kafka_broker.embedded_choice("auto") == "tansu"
    assert Stack(tmp_path / "data").kafka == "tansu"
    assert kafka_broker.embedded_choice("apache") == "apache"
    monkeypatch.setenv("MAPSERVICE_EMBEDDED_KAFKA", "apache")
    assert Stack(tmp_path / "data").kafka == "apache"


def test_up_says_when_kafka_is_tansu_and_what_that_costs(monkeypatch, tmp_path) -> None:
    """Without Java, `up` says Kafka is tansu, why, and that it keeps no record across a restart."""
    monkeypatch.delenv("JAVA_HOME", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path))
    console = Console(record=True, width=300)
    stack = Stack(tmp_path / "data")
    assert embedded_kafka_intro(stack, console) == "tansu, in memory"
    said = console.export_text()
    assert "Kafka is tansu: no Java runtime found" in said
    assert "a restart of it loses every record it held" in said
    assert "no retention" in kafka_keeps(stack)


@pytest.fixture
def node(tmp_path):
    if kafka_broker.java_binary() is None:
        pytest.fail("no Java runtime for Apache Kafka (`make system-deps` installs it)")
    config = kafka_broker.node_for(
        tmp_path / "data", embedded.free_port(), retention_hours=48, retention_bytes=32 * 1024**2
    )
    log = open(tmp_path / "kafka.log", "ab")
    procs = [kafka_broker.start_kafka(config, log)]
    yield config, procs, log
    for proc in procs:
        kafka_broker.stop_process_group(proc)


def test_a_sigkilled_node_restarts_on_its_log_with_every_acknowledged_record(node) -> None:
    """1,000 records acknowledged (acks=all), the JVM SIGKILLed, the node started again on the
    same directory (not formatted again): all 1,000 there, and the broker runs with the
    retention it was given."""
    config, procs, log = node
    bootstrap = f"127.0.0.1:{config.port}"
    admin = AdminClient({"bootstrap.servers": bootstrap})
    admin.create_topics([NewTopic("kept", 3, 1)])["kept"].result(30)
    producer = Producer({"bootstrap.servers": bootstrap, "enable.idempotence": True, "acks": "all"})
    for i in range(1000):
        producer.produce("kept", str(i).encode())
    assert producer.flush(30) == 0
    meta = (config.log_dir / "meta.properties").read_text()

    os.killpg(procs[0].pid, signal.SIGKILL)
    procs[0].wait(10)
    procs.append(
        kafka_broker.start_kafka(
            kafka_broker.node_for(
                config.log_dir.parent.parent,
                config.port,
                retention_hours=48,
                retention_bytes=32 * 1024**2,
            ),
            log,
        )
    )
    assert (config.log_dir / "meta.properties").read_text() == meta  # not formatted again

    consumer = Consumer(
        {"bootstrap.servers": bootstrap, "group.id": "reader", "enable.auto.commit": False}
    )
    consumer.assign([TopicPartition("kept", p, OFFSET_BEGINNING) for p in range(3)])
    values, deadline = set(), time.monotonic() + 30
    while len(values) < 1000 and time.monotonic() < deadline:
        msg = consumer.poll(0.5)
        if msg is not None and not msg.error():
            values.add(int(msg.value()))
    consumer.close()
    assert values == set(range(1000))

    resource = ConfigResource(ConfigResource.Type.BROKER, str(kafka_broker.NODE_ID))
    configs = admin.describe_configs([resource])[resource].result(30)
    assert configs["log.retention.hours"].value == "48"
    assert configs["log.retention.bytes"].value == str(32 * 1024**2)


def test_a_broker_left_running_on_the_data_dir_is_named_not_started_twice(node) -> None:
    """A second start on a directory whose broker still runs (an orphan of a killed `up`)
    fails at once, naming its pid and how to stop it."""
    config, procs, log = node
    with pytest.raises(
        RuntimeError, match=f"still holds .*pid {procs[0].pid}.*kill {procs[0].pid}"
    ):
        kafka_broker.start_kafka(
            kafka_broker.node_for(config.log_dir.parent.parent, embedded.free_port()), log
        )


def test_a_cluster_id_that_starts_with_a_dash_formats_the_log(tmp_path) -> None:
    """One URL-safe cluster id in 32 starts with "-"; the storage tool read such an id as an
    option of its own ("--cluster-id: expected one argument") and the stack did not start."""
    java = kafka_broker.java_binary()
    if java is None:
        pytest.skip("no Java runtime (make test installs it as root)")
    libs = kafka_broker.ensure_jars(None)
    config = kafka_broker.node_for(tmp_path, embedded.free_port())
    config_file = tmp_path / "server.properties"
    config_file.write_text(config.properties())
    (tmp_path / "log4j2.yaml").write_text(kafka_broker.LOG4J2_YAML)
    dashed = "-" + kafka_broker.cluster_id()[1:]
    assert kafka_broker.format_once(java, libs, config_file, config.log_dir, dashed)
    assert f"cluster.id={dashed}" in (config.log_dir / "meta.properties").read_text()


def test_an_unknown_embedded_broker_is_refused_by_name(tmp_path) -> None:
    """start_embedded starts nothing for a name other than apache or tansu, and says which."""
    from mapservice.settings import Settings

    with pytest.raises(ValueError, match="'zookeeper': apache or tansu"):
        kafka_broker.start_embedded("zookeeper", tmp_path, 1, Settings())


def test_consumer_groups_resume_from_their_committed_offsets_after_a_sigkilled_node_restarts(
    node,
) -> None:
    """The history consumer's source in two groups, each having read and committed 300
    records of three partitions: one kept open across the node's SIGKILL and restart, one
    closed before it and opened again after. Both then read exactly the 30 records produced
    after the restart: no group reads the topic again from its start. (Each group's first
    records come in the poll that joins it: were they handed out then, they could never be
    committed, and the group would read them again on every join after.)"""
    from mapservice.adapters.kafka_batch_source import KafkaBatchSource
    from mapservice.settings import Settings

    config, procs, log = node
    bootstrap = f"127.0.0.1:{config.port}"
    admin = AdminClient({"bootstrap.servers": bootstrap})
    admin.create_topics([NewTopic("events", 3, 1)])["events"].result(30)
    producer = Producer({"bootstrap.servers": bootstrap, "enable.idempotence": True})

    def produce(values: range) -> None:
        for i in values:
            producer.produce("events", str(i).encode(), key=str(i).encode())
        assert producer.flush(30) == 0

    def read(source: KafkaBatchSource, count: int, timeout_s: float = 60) -> list[int]:
        got: list[int] = []
        deadline = time.monotonic() + timeout_s
        while len(got) < count and time.monotonic() < deadline:
            records = source.poll(500, 0.5)
            got += [int(r.value) for r in records]
            if records:
                source.commit(records)
        for _ in range(4):  # anything more would come now; the last commits are answered
            got += [int(r.value) for r in source.poll(500, 0.5)]
        return got

    settings = Settings(kafka_bootstrap=bootstrap)
    produce(range(300))
    kept, closed = (KafkaBatchSource(settings, ["events"], g) for g in ("kept", "closed"))
    for source in (kept, closed):
        source.start()
        assert sorted(read(source, 300)) == list(range(300))
    closed.close()

    os.killpg(procs[0].pid, signal.SIGKILL)
    procs[0].wait(10)
    procs.append(kafka_broker.start_kafka(config, log))
    produce(range(300, 330))
    reopened = KafkaBatchSource(settings, ["events"], "closed")
    reopened.start()
    try:
        assert sorted(read(kept, 30)) == list(range(300, 330))
        assert sorted(read(reopened, 30)) == list(range(300, 330))
    finally:
        kept.close()
        reopened.close()


def test_an_idle_controller_appends_no_op_records_as_the_setting_says(
    monkeypatch, tmp_path
) -> None:
    """The embedded node's controller writes its idle no-op records every
    MAPSERVICE_EMBEDDED_KAFKA_METADATA_IDLE_MS, not at Kafka's 500 ms."""
    started: list[kafka_broker.KafkaNodeConfig] = []
    monkeypatch.setattr(kafka_broker, "start_kafka", lambda node, *a, **k: started.append(node))

    def idle_ms(settings: Settings) -> str:
        kafka_broker.start_embedded("apache", tmp_path / "data", 1234, settings)
        props = dict(line.split("=", 1) for line in started[-1].properties().splitlines() if line)
        return props["metadata.max.idle.interval.ms"]

    assert idle_ms(Settings()) == "5000"
    assert idle_ms(Settings(embedded_kafka_metadata_idle_ms=500)) == "500"
    assert idle_ms(Settings(embedded_kafka_metadata_idle_ms=0)) == "0"


@pytest.mark.parametrize("held_by", ["listening", "bound"])
def test_a_controller_port_taken_since_it_was_chosen_is_chosen_again(
    monkeypatch, tmp_path, held_by
) -> None:
    """Another process binding the node's chosen controller port before the node starts
    (free ports are chosen alike by processes side by side) does not stop the start: the
    node alone gets another; a cluster's node keeps the one its voters name."""
    import socket

    launched: list[kafka_broker.KafkaNodeConfig] = []
    monkeypatch.setattr(
        kafka_broker, "launch", lambda config, *a, **k: launched.append(config) or object()
    )
    monkeypatch.setattr(kafka_broker, "wait_ready", lambda *a, **k: None)
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        if held_by == "listening":
            holder.listen()
        taken = holder.getsockname()[1]
        node = kafka_broker.KafkaNodeConfig(
            log_dir=tmp_path / "kafka" / "log", port=embedded.free_port(), controller_port=taken
        )
        kafka_broker.start_kafka(node)
        assert launched[-1].controller_port != taken
        assert embedded.port_is_free(launched[-1].controller_port)
        assert launched[-1].port == node.port and launched[-1].log_dir == node.log_dir

        voter = dataclasses.replace(node, voters=f"1@127.0.0.1:{taken}")
        kafka_broker.start_kafka(voter)
        assert launched[-1] == voter
