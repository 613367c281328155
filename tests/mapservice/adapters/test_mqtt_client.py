"""paho client construction: the gateway's buffered reads."""

from __future__ import annotations


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
    assert sock.recv(1) == b"\x05" and sock.recv(5) == b"hello" and sock.recv(4) == b"\x40\x02\x00\x07"
    assert len(calls) == 1 and sock.pending() == 0 and sock.fileno() == a.fileno()
    assert sock.recv(1) == b""
    a.close()


def test_the_gateway_client_reads_through_a_buffered_socket() -> None:
    """make_client(buffered_reads=True) makes a BufferedClient, whose sockets are buffered."""
    from mapservice.adapters.mqtt_client import BufferedClient, make_client

    assert isinstance(make_client("gw", buffered_reads=True), BufferedClient)
    assert not isinstance(make_client("robot"), BufferedClient)


def test_ack_many_queues_the_pubacks_ack_queues_and_wakes_the_loop_once() -> None:
    """ack_many([(mid, 1), ...]) leaves paho the very packets ack() would, with one wake-up
    byte for all of them (paho's internals changing would fail here, not in production)."""
    import socket

    from mapservice.adapters.mqtt_client import make_client

    one_by_one = make_client("gw-a", manual_ack=True, buffered_reads=True)
    for mid in (7, 8, 65535):
        one_by_one.ack(mid, 1)
    batched = make_client("gw-b", manual_ack=True, buffered_reads=True)
    reader, batched._sockpairW = socket.socketpair()
    try:
        batched.ack_many([(7, 1), (8, 1), (9, 0), (65535, 1)])  # QoS 0 needs no ack
        assert list(batched._out_packet) == list(one_by_one._out_packet)
        reader.setblocking(False)
        assert reader.recv(16) == b"0"
    finally:
        reader.close()
        batched._sockpairW.close()
