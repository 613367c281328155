"""Under `mapservice up --auth` the embedded Apache Kafka serves only the service's
components: a producer without the service's credential (none, a wrong password, an
unknown user, another mechanism) writes nothing any consumer sees, on the clients' port or
the controller's, while robots' poses still go all the way into the history."""

from __future__ import annotations

import time
import uuid

import pytest
from confluent_kafka import OFFSET_BEGINNING, Consumer, Producer, TopicPartition

from mapservice.adapters.ros_map import load_ros_map, meta_for
from mapservice.local.kafka_auth import KAFKA_SERVICE_USER
from mapservice.local.stack import Stack
from tests.fixtures.paths import MAPS

from .conftest import run_stack, wait_for_count
from .test_robot_identity import Robot, now_ms, pose


@pytest.fixture(scope="module")
def stack_and_robot(tmp_path_factory):
    stack = Stack(
        tmp_path_factory.mktemp("stack-kafka-auth"),
        mqtt="mosquitto",
        mqtt_auth=True,
        kafka="apache",
        kafka_auth=True,
    )
    # Before the broker starts (no restart between the gateway's connection and its
    # subscription).
    robot = stack.broker_files.add_robot("kafka-auth-robot")
    yield run_stack(stack, meta_for(load_ros_map(MAPS / "depot.yaml"))), robot
    stack.stop()


@pytest.fixture(scope="module")
def stack(stack_and_robot):
    return stack_and_robot[0]


def intruders(stack: Stack) -> dict[str, dict[str, str]]:
    """Every way to talk to the broker without the service's credential."""
    sasl = {"security.protocol": "SASL_PLAINTEXT"}
    password = stack.service_password(KAFKA_SERVICE_USER, "kafka")
    controller_port = _controller_port(stack)
    return {
        "anonymous": {},
        "wrong password": {
            **sasl,
            "sasl.mechanism": "PLAIN",
            "sasl.username": KAFKA_SERVICE_USER,
            "sasl.password": password[:-1] + ("a" if password[-1] != "a" else "b"),
        },
        "unknown user": {
            **sasl,
            "sasl.mechanism": "PLAIN",
            "sasl.username": "intruder",
            "sasl.password": password,
        },
        "SCRAM, the right password": {
            **sasl,
            "sasl.mechanism": "SCRAM-SHA-512",
            "sasl.username": KAFKA_SERVICE_USER,
            "sasl.password": password,
        },
        "anonymous, the controller's port": {
            "bootstrap.servers": f"127.0.0.1:{controller_port}",
        },
        "the service's user on the controller's port": {
            "bootstrap.servers": f"127.0.0.1:{controller_port}",
            **sasl,
            "sasl.mechanism": "PLAIN",
            "sasl.username": KAFKA_SERVICE_USER,
            "sasl.password": password,
        },
    }


def _controller_port(stack: Stack) -> int:
    properties = (stack.data_dir / "kafka" / "server.properties").read_text()
    listeners = next(line for line in properties.splitlines() if line.startswith("listeners="))
    return int(listeners.rsplit(":", 1)[1])


def records(stack: Stack, topic: str) -> list[bytes]:
    """Every record of `topic`, read with the service's credential."""
    consumer = Consumer(
        {
            **stack.settings().kafka_config(),
            "group.id": f"test-{uuid.uuid4()}",
            "enable.auto.commit": False,
        }
    )
    try:
        partitions = consumer.list_topics(topic, timeout=10).topics[topic].partitions
        consumer.assign([TopicPartition(topic, p, OFFSET_BEGINNING) for p in partitions])
        values, quiet_until = [], time.monotonic() + 3
        while time.monotonic() < quiet_until:
            msg = consumer.poll(0.5)
            if msg is not None and not msg.error():
                values.append(msg.value())
                quiet_until = time.monotonic() + 1
        return values
    finally:
        consumer.close()


def test_a_producer_without_the_services_credential_writes_nothing(stack):
    settings = stack.settings()
    topic = settings.topic_command_events
    # Every intruder at once (each its own producer, their timeouts running side by side):
    # each one's record is refused or times out on its own, whatever the others do.
    producers: dict[str, Producer] = {}
    delivered: dict[str, list] = {}
    for name, conf in intruders(stack).items():
        marker = f"intruder-{name}".encode()
        producers[name] = Producer(
            {
                "bootstrap.servers": stack.kafka_bootstrap,
                **conf,
                "message.timeout.ms": 4000,
                "log_level": 0,
            }
        )
        delivered[name] = []
        try:
            producers[name].produce(
                topic, marker, callback=lambda err, _m, out=delivered[name]: out.append(err)
            )
        except Exception as exc:  # refused before it is queued
            delivered[name].append(exc)
    deadline = time.monotonic() + 15  # each record's own timeout is 4 s
    for producer in producers.values():
        producer.flush(max(0.0, deadline - time.monotonic()))
    outcomes = {name: out[0] if out else "no delivery report" for name, out in delivered.items()}
    for name, out in delivered.items():
        assert out and out[0] is not None, f"{name}: the broker took the record"
    # The service's own credential, for contrast: its record is there, the others' are not.
    producer = Producer({**settings.kafka_config(), "message.timeout.ms": 10000})
    producer.produce(topic, b"the-service")
    assert producer.flush(15) == 0
    seen = records(stack, topic)
    assert b"the-service" in seen
    assert not [v for v in seen if v.startswith(b"intruder-")], outcomes


def test_the_service_still_ingests_end_to_end(stack_and_robot):
    """A robot's poses, through the gateway's producer and the processors' faust consumer
    (both with the service's Kafka credential), are stored."""
    stack, robot = stack_and_robot
    start = now_ms() - 5_000
    client = Robot(stack.mqtt_url, robot.username, robot.password)
    try:
        for k in range(5):
            assert client.publish(
                robot.topics["pose"], pose(robot.robot_id, start + k * 200)
            ).is_published()
    finally:
        client.close()
    assert len(wait_for_count(stack, "pose", robot.robot_id, start, start + 60_000, 5)) == 5
    env = stack.env("gateway")
    assert env["MAPSERVICE_KAFKA_SECURITY_PROTOCOL"] == "SASL_PLAINTEXT"
    assert env["MAPSERVICE_KAFKA_USERNAME"] == KAFKA_SERVICE_USER
