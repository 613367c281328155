"""A subscription the Foxglove SDK lost to its own race is sent again by the gate.

The SDK advertises a channel made while a client is connected before it records that it
did, so a client that subscribes at once can be answered "Unknown channel ID" and dropped
(connected_client.rs, `advertise_channels`). The SDK has no hook between the two steps, so
the race cannot be slowed from outside; the live test puts a shim in front of the real
SDK that answers a new robot's first subscriptions exactly as the SDK does when it loses
(the status, the subscription dropped), which makes the race's outcome certain. With
generated streams, the gate's reading of the SDK's side passes every byte on but the
answers it acts on, and sends each lost subscription again, at most `MAX_ATTEMPTS` times."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import os
import random
import struct

import pytest

from mapservice.api.credentials import Credentials
from mapservice.api.foxglove_frames import SubscriptionCount
from mapservice.api.foxglove_gate import SDK_SUBPROTOCOL, FoxgloveGate, Upstream
from mapservice.api.foxglove_resubscribe import MAX_ATTEMPTS, ServerStream
from tests.api.test_foxglove_frames import frame
from tests.api.test_foxglove_gate import READER, SWITCHING, request, settings

# --- the SDK's side read with generated streams --------------------------------------------


def server_frame(opcode: int, payload: bytes) -> bytes:
    """A server's (unmasked, final) frame."""
    n = len(payload)
    if n < 126:
        head = bytes([0x80 | opcode, n])
    elif n < 65536:
        head = bytes([0x80 | opcode, 126]) + n.to_bytes(2, "big")
    else:
        head = bytes([0x80 | opcode, 127]) + n.to_bytes(8, "big")
    return head + payload


def text(message: dict) -> bytes:
    return server_frame(0x1, json.dumps(message).encode())


def unknown(channel: int) -> bytes:
    return text({"op": "status", "level": 2, "message": f"Unknown channel ID: {channel}"})


@pytest.mark.parametrize("seed", range(30))
def test_the_sdks_side_passes_on_every_byte_but_the_lost_subscriptions_answers(seed):
    rng = random.Random(seed)
    client = SubscriptionCount(1000)
    client.feed(
        frame(0x1, json.dumps({"op": "subscribe", "subscriptions": []}).encode())
    )  # a client stream that has started
    stream = ServerStream(client)
    advertised: set[int] = set()
    subscribed: dict[int, int] = {}  # channel -> subscription
    attempts: dict[int, int] = {}
    ids = itertools.count(1)
    client_at: list[tuple[int, bytes]] = []  # the client's frames, at an offset of the SDK's
    sent, expected_out, expected_again = b"", b"", []
    for _ in range(rng.randrange(20, 80)):
        kind = rng.random()
        channel = rng.randrange(1, 12)
        if kind < 0.2:
            piece = text(
                {"op": "advertise", "channels": [{"id": channel, "topic": f"/t{channel}"}]}
            )
            advertised.add(channel)
        elif kind < 0.27:
            piece = text({"op": "unadvertise", "channelIds": [channel]})
            advertised.discard(channel)
        elif kind < 0.4:  # the client subscribes (its side of the same connection), here
            subscription = next(ids)
            message = {
                "op": "subscribe",
                "subscriptions": [{"id": subscription, "channelId": channel}],
            }
            client_at.append((len(sent), frame(0x1, json.dumps(message).encode())))
            subscribed[channel] = subscription
            continue
        elif kind < 0.65:
            piece = unknown(channel)
            subscription = subscribed.get(channel)
            if (
                channel in advertised
                and subscription is not None
                and attempts.get(subscription, 0) < MAX_ATTEMPTS
            ):
                attempts[subscription] = attempts.get(subscription, 0) + 1
                expected_again.append((subscription, channel))
                sent += piece
                piece = b""
        elif kind < 0.85:  # data, of every length encoding
            piece = server_frame(0x2, os.urandom(rng.choice((0, 5, 125, 126, 300, 70_000))))
        else:
            piece = text({"op": rng.choice(["serverInfo", "status", "time"]), "message": "x"})
        sent += piece
        expected_out += piece
    out, again = b"", []
    fed = 0
    while fed < len(sent) or client_at:
        while client_at and client_at[0][0] == fed:
            client.feed(client_at.pop(0)[1])
        n = rng.choice((1, 2, 3, 7, rng.randrange(1, 90_000)))
        if client_at:
            n = min(n, client_at[0][0] - fed)
        passed, lost = stream.feed(sent[fed : fed + n])
        out += passed
        again += lost
        fed += n
    assert out == expected_out
    assert [(r.subscription_id, r.channel_id) for r in again] == expected_again
    assert all(0 < r.delay_s <= 0.5 for r in again)


def test_a_lost_subscription_is_sent_again_at_most_max_attempts_times():
    client = SubscriptionCount(10)
    client.feed(frame(0x1, b'{"op":"subscribe","subscriptions":[{"id":7,"channelId":3}]}'))
    stream = ServerStream(client)
    stream.feed(text({"op": "advertise", "channels": [{"id": 3, "topic": "/r"}]}))
    delays = []
    for _ in range(MAX_ATTEMPTS):
        passed, again = stream.feed(unknown(3))
        assert passed == b"" and len(again) == 1
        assert json.loads(_unmask(again[0].frame())) == {
            "op": "subscribe",
            "subscriptions": [{"id": 7, "channelId": 3}],
        }
        delays.append(again[0].delay_s)
    assert delays == sorted(delays) and sum(delays) < 5
    assert stream.feed(unknown(3)) == (unknown(3), [])  # then the client hears of it


def _unmask(client_frame: bytes) -> bytes:
    n = client_frame[1] & 0x7F
    at = 2 if n < 126 else 4
    if n == 126:
        n = int.from_bytes(client_frame[2:4], "big")
    mask, payload = client_frame[at : at + 4], client_frame[at + 4 : at + 4 + n]
    return bytes(b ^ mask[i % 4] for i, b in enumerate(payload))


def test_the_gate_sends_it_again_between_two_of_the_clients_messages():
    """Over a raw upstream: the SDK's answer never reaches the client, and the subscription
    goes again only once the client's message then in progress (fragmented) has ended."""

    async def main() -> tuple[bytes, bytes]:
        connected: asyncio.Future = asyncio.get_running_loop().create_future()

        async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            await reader.readuntil(b"\r\n\r\n")
            writer.write(SWITCHING)
            writer.write(text({"op": "advertise", "channels": [{"id": 5, "topic": "/r9"}]}))
            connected.set_result((reader, writer))

        upstream = await asyncio.start_server(serve, "127.0.0.1", 0)
        up_port = upstream.sockets[0].getsockname()[1]

        async def route() -> Upstream:
            return Upstream(up_port)

        s = settings()
        gate = FoxgloveGate(s, Credentials(s), {"/": route})
        port = await gate.start("127.0.0.1", 0)
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(request(f"/?token={READER}"))
        await reader.readuntil(b"\r\n\r\n")
        up_reader, up_writer = await connected
        subscribe = frame(0x1, b'{"op":"subscribe","subscriptions":[{"id":1,"channelId":5}]}')
        first = frame(0x1, b'{"op":"subscribe",', fin=False)
        writer.write(subscribe + first)
        async with asyncio.timeout(5):
            got = await up_reader.readexactly(len(subscribe + first))
        up_writer.write(unknown(5))  # the SDK lost it
        await asyncio.sleep(0.3)  # long past the first delay: held for the message's end
        rest = frame(0x0, b'"subscriptions":[]}')
        writer.write(rest)
        async with asyncio.timeout(5):
            got += await up_reader.readexactly(len(rest))
            again = await up_reader.read(200)
        assert got == subscribe + first + rest  # the client's own bytes, uncut
        to_client = b""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(0.3):
                while chunk := await reader.read(1000):
                    to_client += chunk
        writer.close()
        await gate.stop()
        upstream.close()
        return again, to_client

    again, to_client = asyncio.run(main())
    assert json.loads(_unmask(again)) == {
        "op": "subscribe",
        "subscriptions": [{"id": 1, "channelId": 5}],
    }
    assert b"advertise" in to_client and b"Unknown channel" not in to_client


# --- live, a robot first seen while a client is connected ----------------------------------


def foxglove_client(url: str):
    """A WebSocket client of the SDK's protocol, as Foxglove's app connects."""
    from websockets.asyncio.client import connect

    return connect(url, subprotocols=[SDK_SUBPROTOCOL], compression=None, max_size=None)


class LosingShim:
    """In front of the SDK's server: relays each WebSocket message both ways, but answers
    the first `losses` subscriptions to each channel whose topic starts with `prefix` as the
    SDK answers one it lost (the status; the subscription not passed on)."""

    def __init__(self, sdk_port: int, prefix: str, losses: int) -> None:
        self.sdk_port, self.prefix, self.losses = sdk_port, prefix, losses
        self.lost: dict[int, int] = {}  # channel id -> subscriptions lost so far
        self.port = 0
        self._server = None

    async def start(self) -> None:
        from websockets.asyncio.server import serve

        self._server = await serve(
            self._relay, "127.0.0.1", 0, subprotocols=[SDK_SUBPROTOCOL], compression=None
        )
        self.port = self._server.sockets[0].getsockname()[1]

    def close(self) -> None:
        if self._server is not None:
            self._server.close()

    async def _relay(self, gate_side) -> None:
        losing: set[int] = set()
        async with foxglove_client(f"ws://127.0.0.1:{self.sdk_port}") as sdk:

            async def down() -> None:
                async for message in sdk:
                    if (
                        isinstance(message, str)
                        and (doc := json.loads(message))["op"] == "advertise"
                    ):
                        losing.update(
                            c["id"] for c in doc["channels"] if c["topic"].startswith(self.prefix)
                        )
                    await gate_side.send(message)

            async def up() -> None:
                async for message in gate_side:
                    if (
                        isinstance(message, str)
                        and (doc := json.loads(message))["op"] == "subscribe"
                    ):
                        kept = []
                        for s in doc["subscriptions"]:
                            channel = s["channelId"]
                            if channel in losing and self.lost.get(channel, 0) < self.losses:
                                self.lost[channel] = self.lost.get(channel, 0) + 1
                                await gate_side.send(
                                    json.dumps(
                                        {
                                            "op": "status",
                                            "level": 2,
                                            "message": f"Unknown channel ID: {channel}",
                                        }
                                    )
                                )
                            else:
                                kept.append(s)
                        if not kept:
                            continue
                        message = json.dumps({"op": "subscribe", "subscriptions": kept})
                    await sdk.send(message)

            tasks = [asyncio.ensure_future(down()), asyncio.ensure_future(up())]
            try:
                await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            finally:
                for t in tasks:
                    t.cancel()


@pytest.mark.parametrize("losses", [0, 1, 3], ids=["recorded-in-time", "lost-once", "lost-3x"])
def test_a_live_client_gets_a_robot_first_seen_while_it_is_connected(losses):
    """Connected live through the gate, a client that subscribes to each channel the moment
    it is advertised gets the pose of a robot the live stream brings for the first time,
    and hears nothing of the SDK's lost subscriptions."""
    asyncio.run(_live_client_gets_new_robot(losses))


async def _live_client_gets_new_robot(losses: int) -> None:
    from mapservice.adapters.mcap_channels import pose_topic, state_topic
    from mapservice.core.live_messages import live_record_texts, live_records
    from tests.conftest import pose_event
    from tests.mapservice.adapters.test_foxglove_floods import live_server
    from tests.mapservice.adapters.test_foxglove_scene import T0

    stack = contextlib.AsyncExitStack()
    sdk_port, queue = await stack.enter_async_context(live_server())
    shim = LosingShim(sdk_port, "/robots/r9/", losses)
    await shim.start()
    s = settings()

    async def route() -> Upstream:
        return Upstream(shim.port)

    gate = FoxgloveGate(s, Credentials(s), {"/": route})
    port = await gate.start("127.0.0.1", 0)
    topics: dict[int, str] = {}  # channel id -> topic
    subscribed: dict[int, str] = {}  # subscription id -> topic
    got: dict[str, int] = {}
    statuses: list[str] = []
    try:
        async with foxglove_client(f"ws://127.0.0.1:{port}/?token={READER}") as ws:

            async def read_until(done) -> bool:
                try:
                    async with asyncio.timeout(10):
                        while not done():
                            message = await ws.recv()
                            if isinstance(message, str):
                                doc = json.loads(message)
                                if doc["op"] == "advertise":  # subscribed at once
                                    subscriptions = []
                                    for c in doc["channels"]:
                                        topics[c["id"]] = c["topic"]
                                        subscribed[len(subscribed) + 1] = c["topic"]
                                        subscriptions.append(
                                            {"id": len(subscribed), "channelId": c["id"]}
                                        )
                                    await ws.send(
                                        json.dumps(
                                            {"op": "subscribe", "subscriptions": subscriptions}
                                        )
                                    )
                                elif doc["op"] == "status":
                                    statuses.append(doc["message"])
                            elif message[0] == 0x01:  # message data: its subscription id
                                (subscription,) = struct.unpack_from("<I", message, 1)
                                topic = subscribed[subscription]
                                got[topic] = got.get(topic, 0) + 1
                except TimeoutError:
                    return False
                return True

            assert await read_until(lambda: pose_topic("r0") in got)
            (record,) = live_records([pose_event("r9", T0 + 600_500, 3.0, 4.0)])
            for text_message in live_record_texts(record):
                queue.put_nowait(text_message)
            new_robot = {pose_topic("r9"), state_topic("r9")}
            assert await read_until(lambda: new_robot <= got.keys()), statuses
            assert not [m for m in statuses if m.startswith("Unknown channel ID")]
            assert sum(shim.lost.values()) == losses * len(
                [t for t in topics.values() if t.startswith("/robots/r9/")]
            )
    finally:
        await gate.stop()
        shim.close()
        await stack.aclose()
