"""A simulated robot under robot identities (a real Mosquitto with a password file, an ACL
and the client id made the username, as `mapservice up --auth` runs it): its pose stream,
its command listener and its zone listener share its one connection, so none throws
another off the broker, and it answers every command of a series."""

from __future__ import annotations

import json
import threading
import time

from mapservice.adapters.mqtt_auth import GATEWAY_USER, PROCESSORS_USER
from mapservice.adapters.mqtt_client import make_client
from mapservice.adapters.ros_map import load_ros_map
from mapservice.core.commands import CommandIssued, command_message
from mapservice.robot.commands import command_topic, response_topic
from mapservice.robot.connection import RobotMqtt
from mapservice.robot.sim import SimConfig, sim_robot_id
from mapservice.robot.simrun import SimRunner
from mapservice.robot.zone_feed import ZoneFeed
from tests.fixtures.paths import MAPS

PREFIX = "ident"
KINDS = ("pause", "resume") * 3


class ServiceClient:
    """One of the service's own connections (the gateway's or the processors' user)."""

    def __init__(self, broker, user: str, subscribe: str | None = None) -> None:
        self.received: list[dict] = []
        self.client = make_client(
            f"{user}-{time.time_ns()}",
            username=user,
            password=broker.service_passwords[user],
        )
        ready = threading.Event()

        def on_connect(c, *_):
            if subscribe:
                c.subscribe(subscribe, qos=1)
            else:
                ready.set()

        self.client.on_connect = on_connect
        self.client.on_subscribe = lambda *_: ready.set()
        self.client.on_message = lambda _c, _u, m: self.received.append(json.loads(m.payload))
        self.client.connect("127.0.0.1", broker.port, keepalive=30)
        self.client.loop_start()
        assert ready.wait(10), f"{user} could not connect or subscribe"

    def publish(self, topic: str, doc: dict) -> None:
        self.client.publish(topic, json.dumps(doc), qos=1).wait_for_publish(10)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def wait_until(predicate, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


def test_a_robots_pose_stream_and_its_listeners_share_one_connection(mosquitto_identities):
    broker = mosquitto_identities
    robots = [sim_robot_id(PREFIX, i) for i in range(2)]
    credentials = {r: broker.files.add_robot(r).password for r in robots}
    broker.start()
    fetches = []
    feed = ZoneFeed("http://127.0.0.1:9", None, fetch=lambda: fetches.append(1) or [])
    runner = SimRunner(
        broker.url,
        load_ros_map(MAPS / "depot.yaml"),
        len(robots),
        prefix=PREFIX,
        config=SimConfig(change_every_s=0, dwell_s=0.5),
        mqtt_conn=RobotMqtt(broker.url, credentials),
        zone_feed=feed,
    )
    gateway = ServiceClient(broker, GATEWAY_USER, subscribe=response_topic("+"))
    processors = ServiceClient(broker, PROCESSORS_USER)
    thread = threading.Thread(target=runner.run, kwargs={"seconds": 60}, daemon=True)
    thread.start()
    try:
        assert wait_until(lambda: runner.stats.poses >= 2 * len(robots), 15)
        target = robots[0]  # the robot whose connection the zone listener would share
        now_ms = time.time_ns() // 1_000_000
        for n, kind in enumerate(KINDS):
            command = CommandIssued(f"series-{n}", target, kind, "operator:test", now_ms)
            gateway.publish(command_topic(target), command_message(command))
            assert wait_until(
                lambda n=n: any(
                    a.get("type") == "ack" and a["commandId"] == f"series-{n}"
                    for a in gateway.received
                ),
                10,
            ), f"no answer to command {n} ({kind}); the broker said:\n{broker.log()[-2000:]}"
            # Zone advertisements reach the zone listener meanwhile.
            processors.publish("iot/zones/advertisement", {"version": n})
            time.sleep(0.3)
        acks = [a for a in gateway.received if a.get("type") == "ack"]
        assert [(a["commandId"], a["status"]) for a in acks] == [
            (f"series-{n}", "accepted") for n in range(len(KINDS))
        ]
        assert wait_until(lambda: len(fetches) >= 2, 10)  # the first read, then an advert
        sent = runner.stats.poses
        assert wait_until(lambda: runner.stats.poses > sent, 5)  # still reporting
        log = broker.log()
        assert "already connected" not in log, log[-2000:]
        assert runner.stats.errors == 0
    finally:
        runner.stop()
        thread.join(15)
        gateway.close()
        processors.close()
