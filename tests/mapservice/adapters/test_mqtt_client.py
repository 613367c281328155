"""paho client construction: the gateway's buffered reads."""

from __future__ import annotations

import pytest


def test_buffered_socket_serves_small_reads_from_one_recv_and_reports_pending() -> None:
    """Reads of 1, 1 and n bytes come from one recv; pending() says what is buffered; a
    closed peer reads as b"" once the buffer is empty."""
    import socket

    from mapservice.adapters.mqtt_client import BufferedSocket

    a, b = socket.socketpair()
    calls = []

    class Counting:
        def recv(self, n):
            calls.append(n)
            return a.recv(n)

        def fileno(self):
            return a.fileno()

    sock = BufferedSocket(Counting())
    b.sendall(b"\x30\x05hello\x40\x02\x00\x07")
    b.close()
    assert sock.recv(1) == b"\x30" and sock.pending() == 10
    assert (
        sock.recv(1) == b"\x05" and sock.recv(5) == b"hello" and sock.recv(4) == b"\x40\x02\x00\x07"
    )
    assert len(calls) == 1 and sock.pending() == 0 and sock.fileno() == a.fileno()
    assert sock.recv(1) == b""
    a.close()


def test_the_gateway_client_reads_through_a_buffered_socket() -> None:
    """make_client(buffered_reads=True) makes a BufferedClient, whose sockets are buffered."""
    from mapservice.adapters.mqtt_client import BufferedClient, make_client

    assert isinstance(make_client("gw", buffered_reads=True), BufferedClient)
    assert not isinstance(make_client("robot"), BufferedClient)


def test_ack_many_queues_the_pubacks_ack_would_as_one_write_and_wakes_the_loop_once() -> None:
    """ack_many([(mid, 1), ...]) queues the bytes ack() would, back to back in one packet
    entry, with one wake-up byte for all of them (paho's internals changing would fail
    here, not in production)."""
    import socket

    from mapservice.adapters.mqtt_client import make_client

    one_by_one = make_client("gw-a", manual_ack=True, buffered_reads=True)
    for mid in (7, 8, 65535):
        one_by_one.ack(mid, 1)
    batched = make_client("gw-b", manual_ack=True, buffered_reads=True)
    reader, batched._sockpairW = socket.socketpair()
    try:
        batched.ack_many([(7, 1), (8, 1), (9, 0), (65535, 1)])  # QoS 0 needs no ack
        (entry,) = batched._out_packet
        assert entry["packet"] == b"".join(p["packet"] for p in one_by_one._out_packet)
        assert {k: v for k, v in entry.items() if k not in ("packet", "to_process", "mid")} == {
            k: v
            for k, v in one_by_one._out_packet[0].items()
            if k not in ("packet", "to_process", "mid")
        }
        assert entry["to_process"] == 12
        reader.setblocking(False)
        assert reader.recv(16) == b"0"
    finally:
        reader.close()
        batched._sockpairW.close()


def test_paho_writes_the_batched_pubacks_whole_in_one_send() -> None:
    """paho's own writer sends the one entry ack_many queued with a single send() and
    leaves nothing queued: the broker reads the three PUBACKs."""
    import socket

    from mapservice.adapters.mqtt_client import make_client

    client = make_client("gw", manual_ack=True, buffered_reads=True)
    ours, broker = socket.socketpair()
    sends = []

    class Sock:
        def send(self, data):
            sends.append(bytes(data))
            return ours.send(data)

    client._sock = Sock()
    try:
        client.ack_many([(1, 1), (2, 1), (3, 1)])
        client._packet_write()
        assert len(sends) == 1 and not client._out_packet
        broker.setblocking(False)
        assert broker.recv(64) == b"\x40\x02\x00\x01\x40\x02\x00\x02\x40\x02\x00\x03"
    finally:
        client._sock = None
        ours.close()
        broker.close()


def _read_all(client, packets: bytes, expected: int, got: list) -> None:
    """Feeds `packets` to `client` through a socket pair until `expected` messages came."""
    import select
    import socket

    import paho.mqtt.client as mqtt

    from mapservice.adapters.mqtt_client import BufferedSocket

    ours, broker = socket.socketpair()
    client._sock = BufferedSocket(ours)
    client._state = mqtt._ConnectionState.MQTT_CS_CONNECTED
    try:
        broker.sendall(packets)
        while len(got) < expected:
            assert select.select([ours], [], [], 5)[0], "the client read nothing for 5 s"
            assert client.loop_read() == mqtt.MQTT_ERR_SUCCESS
    finally:
        client._sock = None
        ours.close()
        broker.close()


def test_the_gateway_client_hands_messages_on_without_leaving_cycles_for_the_collector() -> None:
    """200 QoS 1 messages reach on_message with their topic, payload and mid, and leave no
    reference cycle behind (paho's topic matcher left one per message)."""
    import gc

    from mapservice.adapters.mqtt_client import make_client
    from mapservice.bench.fleet.mqtt_packets import publish_packet

    client = make_client("gw", manual_ack=True, buffered_reads=True, clean_session=False)
    got = []
    client.on_message = lambda _c, _u, m: got.append((m.topic, m.payload, m.mid, m.qos))
    packets = b"".join(publish_packet("iot/coordinates/r1", b"{}", mid) for mid in range(1, 201))
    gc.collect()
    gc.disable()
    try:
        _read_all(client, packets, 200, got)
        got_first = got[0]
        got.clear()
        assert gc.collect() < 10  # with the matcher's cycle: ~1,200
    finally:
        gc.enable()
    assert got_first == ("iot/coordinates/r1", b"{}", 1, 1)


def test_the_gateway_client_still_serves_per_topic_callbacks() -> None:
    """A callback added with message_callback_add gets its topic's messages, on_message the rest."""
    from mapservice.adapters.mqtt_client import make_client
    from mapservice.bench.fleet.mqtt_packets import publish_packet

    client = make_client("gw", manual_ack=True, buffered_reads=True, clean_session=False)
    routed, rest = [], []
    client.message_callback_add("iot/chunks/#", lambda _c, _u, m: routed.append(m.mid))
    client.on_message = lambda _c, _u, m: rest.append(m.mid)
    _read_all(
        client,
        publish_packet("iot/chunks/create", b"{}", 1)
        + publish_packet("iot/coordinates/r1", b"{}", 2),
        1,
        rest,
    )
    assert routed == [1] and rest == [2]


@pytest.mark.parametrize("buffered_reads", [False, True], ids=["robot", "gateway"])
def test_a_client_in_a_process_holding_over_a_thousand_files_connects_and_gets_its_messages(
    tmp_path, buffered_reads
) -> None:
    """paho's own loop waits with select(), which takes no descriptor numbered 1024 or more,
    and reports that as a lost connection: in a process with a thousand open files a plain
    paho client never connects (nor says why). Ours polls: it connects, subscribes and gets
    its own QoS 1 message on a socket numbered above 1024."""
    import os
    import resource
    import threading

    from mapservice.adapters.mqtt_client import make_client
    from mapservice.local.stack import Stack

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < 2048:
        pytest.skip(f"this machine allows {hard} open files; the test needs 2048")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, 2048), hard))
    stack = Stack(tmp_path, mqtt="mosquitto")
    held: list[int] = []
    client = None
    try:
        stack.start_mqtt()
        held.append(os.open(os.devnull, os.O_RDONLY))
        while held[-1] < 1100:
            held.append(os.dup(held[0]))
        client = make_client("many-files", buffered_reads=buffered_reads)
        connected, got = threading.Event(), threading.Event()
        client.on_connect = lambda *_: connected.set()
        client.on_message = lambda _c, _u, message: (
            got.set() if message.payload == b"ping" else None
        )
        client.connect("127.0.0.1", stack.mqtt_port)
        client.loop_start()
        assert connected.wait(10), "no CONNACK"
        assert client.socket().fileno() >= 1024
        client.subscribe("many-files/echo", qos=1)
        client.publish("many-files/echo", b"ping", qos=1)
        assert got.wait(10), "the client's own message never came back"
    finally:
        if client is not None:
            client.disconnect()
            client.loop_stop()
        for fd in held:
            os.close(fd)
        stack.stop()
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
