"""The local stack's MQTT broker: starting it (amqtt or Mosquitto), the robots' identities
in its password file and ACL, and restarting it to read them again. A part of `Stack`
(local/stack.py), which mixes it in."""

from __future__ import annotations

import subprocess
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from mapservice.adapters.mqtt_auth import (
    GATEWAY_USER,
    PROCESSORS_USER,
    BrokerFiles,
    RobotCredential,
)
from mapservice.adapters.mqtt_client import make_client, parse_mqtt_url
from mapservice.local import embedded
from mapservice.local.certs import make_server_cert

if TYPE_CHECKING:
    from mapservice.settings import Settings

BROKER_SIZE_HEADROOM = 8  # Mosquitto's message_size_limit over MAPSERVICE_MAX_MESSAGE_BYTES


def mqtt_accepts(
    mqtt_url: str, username: str | None, password: str | None, timeout_s: float = 5.0, **tls
) -> bool:
    """Whether the broker at `mqtt_url` accepts this credential (its CONNACK), for waiting
    until a reloaded password file is in force and for tests."""
    host, port, use_tls = parse_mqtt_url(mqtt_url)
    client = make_client(
        f"probe-{username}-{time.time_ns()}",
        username=username,
        password=password,
        tls=use_tls,
        **tls,
    )
    answered, result = threading.Event(), []

    def on_connect(_c, _u, _f, reason_code, _p) -> None:
        result.append(not reason_code.is_failure)
        answered.set()

    client.on_connect = on_connect
    try:
        client.connect(host, port, keepalive=10)
    except OSError:
        return False
    client.loop_start()
    try:
        answered.wait(timeout_s)
        return bool(result and result[0])
    finally:
        client.disconnect()
        client.loop_stop()


class StackMqtt:
    """The MQTT broker's part of `Stack`."""

    if TYPE_CHECKING:  # what it uses of the Stack it is mixed into
        data_dir: Path
        tls_dir: Path
        mqtt: str
        mqtt_url: str
        mqtt_port: int
        mqtt_ws_port: int
        mqtt_auth: bool
        mqtt_tls: bool
        mqtt_tls_port: int
        broker_files: BrokerFiles
        procs: dict[str, subprocess.Popen]
        _broker_files_read: tuple
        _broker_files_seen: tuple

        def _preexec(self): ...
        def _record(self) -> None: ...
        def _log(self, name: str): ...
        def settings(self) -> Settings: ...
        def service_password(self, username: str, system: str = "mqtt") -> str: ...
        def is_alive(self, name: str) -> bool: ...

    def start_mqtt(self) -> subprocess.Popen:
        embedded.stop(self.procs.pop("mqtt", None))
        if self.mqtt == "amqtt":
            self.procs["mqtt"] = embedded.start_amqtt(
                self.mqtt_port,
                self._log("amqtt"),
                ws_port=self.mqtt_ws_port,
                preexec_fn=self._preexec,
            )
        elif self.mqtt == "mosquitto":
            self.procs["mqtt"] = embedded.start_mosquitto(
                self.mqtt_port,
                self.data_dir,
                self._log("mosquitto"),
                ws_port=self.mqtt_ws_port,
                options=self._mosquitto_options(),
                preexec_fn=self._preexec,
            )
        else:
            raise RuntimeError(f"the MQTT broker at {self.mqtt} is not this stack's to start")
        self._record()
        self._broker_files_read = self._broker_files_seen = self._broker_files_state()
        return self.procs["mqtt"]

    def _broker_files_state(self) -> tuple:
        state = []
        files = self.broker_files
        for path in (files.password_file, files.acl_file, files.dynsec_file):
            try:
                info = path.stat()
                state.append((info.st_mtime_ns, info.st_size, info.st_ino))
            except FileNotFoundError:
                state.append(None)
        return tuple(state)

    def reload_mqtt_if_files_changed(self) -> bool:
        """Restarts Mosquitto (reload_mqtt) when its password file or ACL changed since it
        read them (`mapservice robot add/remove` while `up` runs) and the change held still
        since the last call; whether it did."""
        if not self.mqtt_auth or not self.is_alive("mqtt"):
            return False
        state = self._broker_files_state()
        if state == self._broker_files_read:
            return False
        if state != self._broker_files_seen:
            self._broker_files_seen = state
            return False
        self.reload_mqtt()
        return True

    def _mosquitto_options(self) -> embedded.MosquittoOptions:
        """The store in the data dir (sessions and queued QoS 1 messages survive a restart),
        password file and ACL (with the service users' passwords), and the TLS listener."""
        # The broker refuses a message far over the gateway's maximum before it is stored
        # (four 50 MB messages for an offline session made a 200 MB store that was rewritten
        # every second); one up to BROKER_SIZE_HEADROOM times over still reaches the gateway,
        # which dead-letters it as `oversized` with its size: the sender's only trace, as a
        # 2019 robot (MQTT 3.1.1) learns nothing from a broker that drops its message.
        options = embedded.MosquittoOptions(
            store_dir=self.data_dir / "mosquitto",
            message_size_limit=BROKER_SIZE_HEADROOM * self.settings().max_message_bytes,
        )
        if self.mqtt_auth:
            for user in (GATEWAY_USER, PROCESSORS_USER):
                self.broker_files.set_service_user(user, self.service_password(user))
            files = self.broker_files
            for path in (files.password_file, files.acl_file, files.dynsec_file):
                path.chmod(0o600)  # the broker runs as this user (or as root): it reads them
            options = replace(
                options,
                password_file=files.password_file,
                acl_file=files.acl_file,
                dynsec_file=files.dynsec_file,
            )
        if self.mqtt_tls:
            options = replace(
                options, tls_port=self.mqtt_tls_port, tls=make_server_cert(self.tls_dir)
            )
        return options

    def add_robot(self, robot_id: str, *, legacy_chunks: bool = False) -> RobotCredential:
        """A robot's own MQTT credential, in force once this returns (the broker restarted
        to read its files and accepted the new user)."""
        if not self.mqtt_auth:
            raise RuntimeError("this stack runs without robot identities (mqtt_auth=False)")
        credential = self.broker_files.add_robot(robot_id, legacy_chunks=legacy_chunks)
        self.reload_mqtt()
        deadline = time.monotonic() + 10
        while not mqtt_accepts(self.mqtt_url, credential.username, credential.password):
            if time.monotonic() > deadline:
                raise RuntimeError(f"the broker did not accept robot {robot_id}'s new credential")
            time.sleep(0.1)
        return credential

    def robot_credentials(self, robot_ids: list[str]) -> Path:
        """Every robot in `robot_ids` with its own MQTT credential, kept (for the simulators'
        `--credentials`) in DATA_DIR/secrets/robots.json; a robot that already has one in
        both the broker's password file and that file keeps it. Returns the file."""
        from mapservice.robot.connection import load_credentials, save_credential

        path = self.data_dir / "secrets" / "robots.json"
        saved = load_credentials(path) if path.exists() else {}
        known = set(self.broker_files.robots())
        for robot_id in robot_ids:
            if robot_id in saved and robot_id in known:
                continue
            credential = self.broker_files.add_robot(robot_id, rotate=robot_id in known)
            save_credential(path, robot_id, credential.password)
        self.reload_mqtt()
        return path

    def reload_mqtt(self) -> None:
        """A running Mosquitto reads its password file and ACL again: stopped (it saves its
        store: sessions and queued messages) and started again from that store; clients
        reconnect and resend what was not acknowledged. Never SIGHUP: Mosquitto 2.0.11 that
        started from its store and then got SIGHUP (with an ACL) no longer delivers to the
        persistent sessions it restored, the gateway's among them, so every message robots
        publish until the gateway reconnects is lost (tests/mapservice/local/
        test_mosquitto_reload.py)."""
        proc = self.procs.get("mqtt")
        if self.mqtt == "mosquitto" and proc is not None and proc.poll() is None:
            self.start_mqtt()
