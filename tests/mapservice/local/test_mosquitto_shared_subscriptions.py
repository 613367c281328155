"""No robot, VDA 5050 vehicle or master control joins a shared subscription on the broker
the local stack runs (a real Mosquitto with the password file, the ACL and the dynamic
security plugin's file that BrokerFiles writes): every `$share/<group>/<filter>` they send,
for every topic robots deal with, wildcards included, is refused in its SUBACK, publishing
to a `$share/...` topic is refused, and the gateways' group gets every message although
robots tried to join it. The service's users still subscribe through their group."""

from __future__ import annotations

import time

import pytest

from mapservice.adapters.mqtt_auth import GATEWAY_USER, PROCESSORS_USER
from mapservice.settings import VDA5050_SUBTOPICS, Settings
from tests.fixtures.mosquitto import ProbeClient as Client
from tests.fixtures.mosquitto import mosquitto_identities  # noqa: F401 (a fixture)

SETTINGS = Settings(mqtt_share_group="mapservice")
ROBOT, VEHICLE, MASTER = "r1", "Acme/001", "mapservice-master-plant"
GROUPS = (SETTINGS.mqtt_share_group, "g", "robots")


def robot_facing_filters(identity: str) -> list[str]:
    """Every topic filter of the service a robot publishes on or reads, its own and the
    fleet's, and wildcards over them."""
    s = SETTINGS
    vda = [f"{s.vda5050_interface}/v2/{VEHICLE}/{sub}" for sub in (*VDA5050_SUBTOPICS, "order")]
    own = [f"{s.coordinate_topic.rstrip('#')}{identity}", s.command_topic(identity)]
    gateway = [f.removeprefix(f"$share/{s.mqtt_share_group}/") for f in s.mqtt_subscriptions]
    return [
        *gateway,
        *own,
        *vda,
        f"{s.vda5050_interface}/+/+/+/instantActions",
        s.advertisement_topic,
        s.zone_advertisement_topic,
        "#",
        "+",
        "iot/#",
        "iot/+/+",
        f"{s.vda5050_interface}/#",
    ]


@pytest.fixture
def broker(mosquitto_identities):  # noqa: F811 (the fixture, imported above)
    broker = mosquitto_identities
    broker.passwords = {i: broker.files.add_robot(i).password for i in (ROBOT, VEHICLE, MASTER)}
    broker.start()
    return broker


def test_robots_cannot_subscribe_to_any_shared_subscription(broker):
    gateway = Client(broker.port, GATEWAY_USER, broker.service_passwords[GATEWAY_USER])
    try:
        codes = gateway.subscribe(SETTINGS.mqtt_subscriptions)
        assert all(not c.is_failure for c in codes), codes  # the gateways' group still works
    finally:
        gateway.close()
    tried = 0
    for identity in (ROBOT, VEHICLE, MASTER):
        client = Client(broker.port, identity, broker.passwords[identity])
        try:
            filters = [
                f"$share/{group}/{f}" for group in GROUPS for f in robot_facing_filters(identity)
            ]
            codes = client.subscribe(filters)
            granted = [f for f, c in zip(filters, codes, strict=True) if not c.is_failure]
            assert granted == [], f"{identity} joined shared subscriptions: {granted}"
            tried += len(filters)
            # What it may read without a group stays readable (the refusal is about $share).
            own = SETTINGS.advertisement_topic
            assert not client.subscribe([own])[0].is_failure
        finally:
            client.close()
    assert tried >= 3 * len(GROUPS) * 15


def test_robots_cannot_publish_on_a_shared_subscription_topic(broker):
    for identity in (ROBOT, VEHICLE, MASTER):
        client = Client(broker.port, identity, broker.passwords[identity])
        try:
            for group in GROUPS:
                for topic in robot_facing_filters(identity):
                    if "+" in topic or "#" in topic:
                        continue  # not a topic one can publish on
                    code = client.publish(f"$share/{group}/{topic}")
                    assert code is not None and code.is_failure, (identity, group, topic, code)
        finally:
            client.close()


def test_the_gateways_group_gets_every_message_while_robots_try_to_join_it(broker):
    """A robot sends 100 poses while every identity has tried to join the gateways' group:
    the group (one gateway here) receives all 100."""
    group = f"$share/{SETTINGS.mqtt_share_group}/{SETTINGS.coordinate_topic}"
    gateway = Client(broker.port, GATEWAY_USER, broker.service_passwords[GATEWAY_USER])
    intruders = [Client(broker.port, i, broker.passwords[i]) for i in (ROBOT, VEHICLE, MASTER)]
    try:
        assert not gateway.subscribe([group])[0].is_failure
        for intruder in intruders:
            intruder.subscribe([group])
        robot = intruders[0]
        pose_topic = f"{SETTINGS.coordinate_topic.rstrip('#')}{ROBOT}"
        for n in range(100):
            code = robot.publish(pose_topic, f'{{"n": {n}}}'.encode())
            assert code is not None and not code.is_failure, code
        deadline = time.monotonic() + 10
        while len(gateway.received) < 100 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)  # nothing beyond the 100 either
        assert len(gateway.received) == 100, f"the gateways got {len(gateway.received)} of 100"
        assert all(not i.received for i in intruders)
    finally:
        for c in (gateway, *intruders):
            c.close()


def test_the_processors_user_is_not_limited_by_the_robots_rule(broker):
    """Only robots, vehicles and master controls are in the plugin's file: the service's
    users keep what the acl_file gives them."""
    processors = Client(broker.port, PROCESSORS_USER, broker.service_passwords[PROCESSORS_USER])
    try:
        code = processors.publish(SETTINGS.advertisement_topic)
        assert code is not None and not code.is_failure
    finally:
        processors.close()
