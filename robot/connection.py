"""How the robot tools reach the MQTT broker: address, TLS and, where the broker checks
robot identities, each robot's own credential (username = robotId).

A credentials file is JSON, `{"<robotId>": "<password>", ...}`, as `mapservice robot add
--save FILE` writes it. Without one, every robot connects anonymously, as in 2019. With
one, each robot has a connection of its own (the broker knows who publishes), and chunks go
to the robot's own chunk topic (`iot/chunks/create/<robotId>`), which is the only chunk
topic an authenticated robot may use unless an operator opened the 2019 one for it.

A robot has ONE connection: the broker makes a client's id its username
(`use_username_as_clientid`), so a second connection with the same credential takes the
first one's place and the two throw each other off in turn. Whatever else a tool reads on
a robot's behalf (commands, zone advertisements) subscribes on that connection
(`subscribe_always`, `RobotClients.subscribe`).
"""

from __future__ import annotations

import json
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import paho.mqtt.client as mqtt

from mapservice.adapters.mqtt_client import MqttTls, make_client, parse_mqtt_url

LEGACY_CHUNK_TOPIC = "iot/chunks/create"
ROBOT_CHUNK_PREFIX = "iot/chunks/create/"


def load_credentials(path: str | Path) -> dict[str, str]:
    """robotId -> password from a credentials file."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"cannot read the robot credentials file {path}: {exc}") from exc
    if not isinstance(doc, dict) or not all(
        isinstance(k, str) and isinstance(v, str) for k, v in doc.items()
    ):
        raise ValueError(f"{path}: a robot credentials file is a JSON object robotId -> password")
    return doc


def save_credential(path: str | Path, robot_id: str, password: str) -> None:
    """Adds or replaces one robot's password in a credentials file (mode 0600)."""
    path = Path(path)
    creds = load_credentials(path) if path.exists() else {}
    creds[robot_id] = password
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600), "w") as file:
        json.dump(creds, file, indent=2, sort_keys=True)
        file.write("\n")
    os.replace(tmp, path)


@dataclass(frozen=True)
class RobotMqtt:
    """The broker as robots see it."""

    url: str
    credentials: dict[str, str] | None = None  # robotId -> password; None: anonymous
    tls: MqttTls | None = None
    # None: the robot's own chunk topic when robots have credentials, else the 2019 one.
    per_robot_chunk_topic: bool | None = None

    @property
    def authenticated(self) -> bool:
        return self.credentials is not None

    def chunk_topic(self, robot_id: str) -> str:
        own = (
            self.authenticated if self.per_robot_chunk_topic is None else self.per_robot_chunk_topic
        )
        return f"{ROBOT_CHUNK_PREFIX}{robot_id}" if own else LEGACY_CHUNK_TOPIC

    def password(self, robot_id: str) -> str:
        if self.credentials is None or robot_id not in self.credentials:
            raise ValueError(
                f"robot {robot_id!r} has no credential in the credentials file; "
                f"add it with `mapservice robot add {robot_id} --save FILE`"
            )
        return self.credentials[robot_id]

    def check(self, robot_ids: list[str]) -> None:
        """Fails early, naming every robot without a credential."""
        if self.credentials is not None:
            missing = [r for r in robot_ids if r not in self.credentials]
            if missing:
                raise ValueError(
                    f"{len(missing)} robots have no credential in the credentials "
                    f"file (e.g. {', '.join(missing[:3])}); add each with "
                    "`mapservice robot add <robotId> --save FILE`"
                )

    def client(self, client_id: str, robot_id: str | None = None, **kwargs) -> mqtt.Client:
        """A paho client for one robot (its credential, if any) or, without robot_id, an
        anonymous one (a shared connection of robots without credentials)."""
        _, _, tls = parse_mqtt_url(self.url)
        username = password = None
        if self.authenticated and robot_id is not None:
            username, password = robot_id, self.password(robot_id)
        return make_client(
            client_id, username=username, password=password, tls=tls, tls_files=self.tls, **kwargs
        )

    def connect(self, client: mqtt.Client, timeout_s: float = 10.0, who: str = "robot") -> None:
        """Connects and starts the client's network thread; waits for the broker's answer when
        the robot has a credential, so a refused one fails here instead of reconnecting forever."""
        host, port, _ = parse_mqtt_url(self.url)
        answered, refused = threading.Event(), []
        previous = client.on_connect

        def on_connect(c, userdata, flags, reason_code, properties=None) -> None:
            if reason_code.is_failure:
                refused.append(str(reason_code))
            answered.set()
            if previous is not None:
                previous(c, userdata, flags, reason_code, properties)

        client.on_connect = on_connect
        client.connect(host, port, keepalive=30)
        client.loop_start()
        if not self.authenticated:
            return
        if not answered.wait(timeout_s):
            client.loop_stop()
            raise OSError(f"no answer from the MQTT broker at {self.url} within {timeout_s:.0f} s")
        if refused:
            client.loop_stop()
            client.disconnect()
            raise PermissionError(
                f"the MQTT broker at {self.url} refused {who}'s credential: {refused[0]}"
            )


def subscribe_always(client: mqtt.Client, topics: list[tuple[str, int]], on_message=None) -> None:
    """Subscribes `client` to `topics` now (if connected) and again on each reconnect; with
    `on_message`, the messages of these topics go to it (paho routes them by filter), the
    client's other subscriptions keep their own handler."""
    if on_message is not None:
        for topic, _ in topics:
            client.message_callback_add(topic, on_message)
    previous = client.on_connect

    def on_connect(c, userdata, flags, reason_code, properties=None) -> None:
        if previous is not None:
            previous(c, userdata, flags, reason_code, properties)
        if not reason_code.is_failure:
            c.subscribe(topics)

    client.on_connect = on_connect
    if client.is_connected():
        client.subscribe(topics)


class RobotClients:
    """The connections of a fleet: one per robot when robots have credentials (the broker
    then checks each robot's topics), one shared anonymous connection otherwise."""

    def __init__(
        self, conn: RobotMqtt, robot_ids: list[str], client_prefix: str, on_disconnect=None
    ) -> None:
        conn.check(robot_ids)
        self.conn = conn
        self.robot_ids = list(robot_ids)
        self.client_prefix = client_prefix
        self.on_disconnect = on_disconnect
        self.clients: dict[str | None, mqtt.Client] = {}

    def connect(self) -> None:
        keys: list[str | None] = self.robot_ids if self.conn.authenticated else [None]
        try:
            for robot_id in keys:
                client = self.conn.client(
                    f"{self.client_prefix}-{robot_id or 'fleet'}-{time.time_ns() % 10**9}", robot_id
                )
                if self.on_disconnect is not None:
                    client.on_disconnect = self.on_disconnect
                self.conn.connect(client, who=robot_id or "the fleet")
                self.clients[robot_id] = client
        except BaseException:
            self.close()
            raise

    def publish(
        self, robot_id: str, topic: str, payload: bytes, qos: int = 1
    ) -> mqtt.MQTTMessageInfo:
        client = self.clients[robot_id if self.conn.authenticated else None]
        return client.publish(topic, payload, qos=qos)

    def chunk_topic(self, robot_id: str) -> str:
        return self.conn.chunk_topic(robot_id)

    def subscribe(self, topic: str, on_message, qos: int = 1) -> str | None:
        """Reads `topic` on an existing connection (the first robot's own, or the shared
        anonymous one), never on one more: a second connection under a robot's credential
        would take over the first. Returns whose connection reads it (None: there is no
        connection, as a fleet of no robot with credentials has none)."""
        if not self.clients:
            return None
        key = next(iter(self.clients))
        subscribe_always(self.clients[key], [(topic, qos)], on_message)
        return key or "the fleet"

    def close(self) -> None:
        for client in self.clients.values():
            client.loop_stop()
            client.disconnect()
        self.clients.clear()


def add_mqtt_arguments(parser, *, many: bool) -> None:
    """The robot tools' flags for identities and TLS (sim, robot, drive)."""
    parser.add_argument(
        "--credentials",
        default=None,
        metavar="FILE",
        help="JSON file robotId -> MQTT password (`mapservice robot add ID --save "
        "FILE` writes it): "
        + ("each robot connects as itself" if many else "the robot connects as itself")
        + "; default: anonymous, as in 2019",
    )
    parser.add_argument(
        "--chunk-topic",
        choices=["auto", "legacy", "per-robot"],
        default="auto",
        help="where chunks go: the 2019 iot/chunks/create (legacy) or the robot's "
        "own iot/chunks/create/<robotId> (per-robot); auto: per-robot with "
        "--credentials, else legacy",
    )
    parser.add_argument(
        "--mqtt-ca-file",
        default=None,
        metavar="PEM",
        help="CA certificate that signs the broker's (with an mqtts:// URL); "
        "default: MAPSERVICE_MQTT_CA_FILE, else the system's CAs",
    )
    parser.add_argument(
        "--mqtt-cert-file",
        default=None,
        metavar="PEM",
        help="client certificate for mutual TLS (with --mqtt-key-file)",
    )
    parser.add_argument(
        "--mqtt-key-file", default=None, metavar="PEM", help="private key of --mqtt-cert-file"
    )


def robot_mqtt_from_args(args, url: str, default_ca_file=None) -> RobotMqtt:
    """The RobotMqtt the flags of add_mqtt_arguments describe."""
    _, _, tls_url = parse_mqtt_url(url)
    ca_file = args.mqtt_ca_file or (default_ca_file if tls_url else None)
    tls = (
        MqttTls(ca_file, args.mqtt_cert_file, args.mqtt_key_file)
        if (ca_file or args.mqtt_cert_file or args.mqtt_key_file)
        else None
    )
    credentials = load_credentials(args.credentials) if args.credentials else None
    per_robot = {"auto": None, "legacy": False, "per-robot": True}[args.chunk_topic]
    return RobotMqtt(url, credentials, tls, per_robot)
