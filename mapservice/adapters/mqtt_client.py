"""paho-mqtt client construction shared by the gateway, the processors, the robots and tests."""

from __future__ import annotations

import select
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlparse

import paho.mqtt.client as mqtt

from mapservice.settings import Settings


@dataclass(frozen=True)
class MqttTls:
    """TLS files of one MQTT client: the CA that signs the broker's certificate (None: the
    system's CAs) and, for mutual TLS, a client certificate with its key."""

    ca_file: str | Path | None = None
    cert_file: str | Path | None = None
    key_file: str | Path | None = None

    def __post_init__(self) -> None:
        if (self.cert_file is None) != (self.key_file is None):
            raise ValueError(
                "an MQTT client certificate needs its key file (and the other way round)"
            )


def parse_mqtt_url(url: str) -> tuple[str, int, bool]:
    parsed = urlparse(url if "://" in url else f"mqtt://{url}")
    if parsed.scheme not in ("mqtt", "mqtts", "tcp", "ssl"):
        raise ValueError(f"MQTT URL {url!r}: use mqtt://host:port or mqtts://host:port")
    tls = parsed.scheme in ("mqtts", "ssl")
    return parsed.hostname or "127.0.0.1", parsed.port or (8883 if tls else 1883), tls


class BufferedSocket:
    """paho's socket with a read buffer: one recv() of up to READ_SIZE bytes serves many
    packets.

    paho reads a packet's first byte, each byte of its length and its body with a recv()
    apiece, and one packet per select(): 4-5 system calls per message, a large part of the
    gateway's CPU at thousands of messages a second. paho's loop asks a socket for
    `pending()` (meant for TLS's buffered bytes) and reads on without select() while it
    has some, so buffered packets never wait for the socket to become readable again."""

    READ_SIZE = 256 * 1024

    def __init__(self, sock) -> None:
        self._sock = sock
        self._buffer = b""
        self._pos = 0

    def recv(self, size: int) -> bytes:
        if self._pos >= len(self._buffer):
            data = self._sock.recv(max(size, self.READ_SIZE))  # BlockingIOError, b"" at EOF
            if len(data) <= size:
                return data
            self._buffer, self._pos = data, 0
        end = self._pos + size
        out = self._buffer[self._pos : end]
        self._pos = end
        if end >= len(self._buffer):
            self._buffer, self._pos = b"", 0
        return out

    def buffered(self) -> int:
        """Bytes read from the socket and not handed out yet."""
        return len(self._buffer) - self._pos

    def pending(self) -> int:
        inner = getattr(self._sock, "pending", None)
        return len(self._buffer) - self._pos + (inner() if inner is not None else 0)

    def __getattr__(self, name: str):
        return getattr(self._sock, name)


class PollingClient(mqtt.Client):
    """A paho client that waits on its socket with poll(), not select().

    paho's network loop calls select(), which takes no file descriptor numbered 1024 or
    above, and paho turns the resulting ValueError into "connection lost": in a process
    holding a thousand files or sockets (an API with many WebSocket clients, a long test
    run) every connection attempt fails silently and forever (paho.mqtt.python issue 819).
    This is paho's `_loop`, step for step, with poll() in select()'s place."""

    def _loop(self, timeout: float = 1.0) -> mqtt.MQTTErrorCode:
        sock = self._sock
        if sock is None or timeout < 0.0 or not hasattr(select, "poll"):
            return super()._loop(timeout)  # paho's own answer (and Windows, which lacks poll)
        pending_bytes = sock.pending() if hasattr(sock, "pending") else 0
        wake = self._sockpairR
        poller = select.poll()
        try:
            sock_fd = sock.fileno()
            poller.register(sock_fd, select.POLLIN | (select.POLLOUT if self.want_write() else 0))
            if wake is not None:
                poller.register(wake, select.POLLIN)
            ready = dict(poller.poll(0 if pending_bytes > 0 else timeout * 1000))
        except (TypeError, ValueError, OSError):
            # A socket closed under the loop (disconnect() from another thread): paho's
            # loop reports the connection lost and leaves a disconnect in progress be.
            if self._state not in (
                mqtt._ConnectionState.MQTT_CS_DISCONNECTING,
                mqtt._ConnectionState.MQTT_CS_DISCONNECTED,
            ):
                self._state = mqtt._ConnectionState.MQTT_CS_CONNECTION_LOST
            return mqtt.MQTTErrorCode.MQTT_ERR_CONN_LOST

        sock_events = ready.get(sock_fd, 0)
        # A hang-up or error reads as EOF, which is how paho learns the connection is gone.
        if sock_events & ~select.POLLOUT or pending_bytes > 0:
            rc = self.loop_read()
            if rc or self._sock is None:
                return rc
        write = bool(sock_events & select.POLLOUT)
        if wake is not None and ready.get(wake.fileno(), 0):
            # publish() and friends wrote a byte to wake the loop: write what they queued.
            write = True
            try:
                wake.recv(10000)
            except BlockingIOError:
                pass
        if write:
            rc = self.loop_write()
            if rc or self._sock is None:
                return rc
        return self.loop_misc()


class BufferedClient(PollingClient):
    """A paho client reading through a `BufferedSocket` (the gateway's: it receives every
    robot's messages) and acknowledging many messages at once (`ack_many`)."""

    def ack_many(self, acks: Iterable[tuple[int, int]]) -> None:
        """Acknowledges (mid, qos) pairs like `ack()`, in one write and one wake-up.

        `ack()` queues one 4-byte PUBACK per message, which paho then writes with a send()
        of its own, after a wake-up byte on its socket pair: at thousands of messages a
        second, a system call per message.
        Here the QoS 1 PUBACKs (the bytes `ack()` would queue, back to back: a test
        compares them) go into one queued write, and one byte wakes paho's thread.
        """
        pubacks = bytearray()
        for mid, qos in acks:
            if qos == 1 and self._manual_ack:
                pubacks += struct.pack("!BBH", mqtt.PUBACK, 2, mid)
            else:
                self.ack(mid, qos)
        if not pubacks:
            return
        # paho writes a queued packet until `to_process` bytes are out and acts on nothing
        # of a PUBACK's but its bytes (_packet_write), so one entry can hold many (its
        # "mid" is read only for PUBLISH).
        self._out_packet.append(
            {
                "command": mqtt.PUBACK,
                "mid": 0,
                "qos": 1,
                "pos": 0,
                "to_process": len(pubacks),
                "packet": bytes(pubacks),
                "info": None,
            }
        )
        if self._sockpairW is not None:
            try:
                self._sockpairW.send(b"0")
            except BlockingIOError:
                pass
        self._call_socket_register_write()

    def _create_socket(self):
        return BufferedSocket(super()._create_socket())

    def _handle_on_message(self, message: mqtt.MQTTMessage) -> None:
        """Calls `on_message` without paho's topic matcher when no per-topic callback is
        registered (`message_callback_add`; the gateway registers none).

        paho matches every message against those callbacks first; its matcher is a
        recursive closure, a reference cycle per message that only the cyclic garbage
        collector frees (6 objects a message: BENCHMARKS.md).
        """
        if self._on_message_filtered._root._children:
            super()._handle_on_message(message)
            return
        on_message = self.on_message
        if on_message is None:
            return
        with self._in_callback_mutex:
            try:
                on_message(self, self._userdata, message)
            except Exception as err:
                self._easy_log(mqtt.MQTT_LOG_ERR, "Caught exception in on_message: %s", err)
                if not self.suppress_exceptions:
                    raise

    def loop_read(self, max_packets: int = 1) -> mqtt.MQTTErrorCode:
        """Reads every whole packet already buffered, not one: paho reads one packet per
        call (and per select()) unless it has messages of its own in flight."""
        rc = super().loop_read(max_packets)
        while (
            rc == mqtt.MQTT_ERR_SUCCESS
            and isinstance(self._sock, BufferedSocket)
            and self._sock.buffered() > 0
        ):
            rc = super().loop_read(max_packets)
        return rc


def make_client(
    client_id: str,
    *,
    clean_session: bool = True,
    manual_ack: bool = False,
    username: str | None = None,
    password: str | None = None,
    tls: bool = False,
    tls_files: MqttTls | None = None,
    protocol: int = mqtt.MQTTv311,
    buffered_reads: bool = False,
) -> mqtt.Client:
    """A paho client; `tls` (the URL said mqtts://) turns TLS on, with `tls_files` if given;
    `buffered_reads` for a client that receives many messages (`BufferedClient`)."""
    if tls_files is not None and not tls and (tls_files.ca_file or tls_files.cert_file):
        raise ValueError(
            "MQTT CA or client certificate given for a plain mqtt:// URL; use mqtts://"
        )
    client = (BufferedClient if buffered_reads else PollingClient)(
        mqtt.CallbackAPIVersion.VERSION2,
        client_id=client_id,
        clean_session=clean_session if protocol != mqtt.MQTTv5 else None,
        protocol=protocol,
        manual_ack=manual_ack,
    )
    if username:
        client.username_pw_set(username, password)
    if tls:
        files = tls_files or MqttTls()
        client.tls_set(
            ca_certs=str(files.ca_file) if files.ca_file else None,
            certfile=str(files.cert_file) if files.cert_file else None,
            keyfile=str(files.key_file) if files.key_file else None,
        )
    client.max_inflight_messages_set(1000)
    client.max_queued_messages_set(0)
    return client


def settings_tls(settings: Settings) -> MqttTls:
    """The service's MQTT TLS files (MAPSERVICE_MQTT_CA_FILE, _CERT_FILE, _KEY_FILE)."""
    return MqttTls(settings.mqtt_ca_file, settings.mqtt_cert_file, settings.mqtt_key_file)


def service_client(settings: Settings, client_id: str, **kwargs) -> mqtt.Client:
    """A client of the service (gateway, advertiser) with its credential and TLS settings."""
    _, _, tls = parse_mqtt_url(settings.mqtt_url)
    return make_client(
        client_id,
        username=settings.mqtt_username,
        password=settings.mqtt_password.get_secret_value() if settings.mqtt_password else None,
        tls=tls,
        tls_files=settings_tls(settings),
        **kwargs,
    )
