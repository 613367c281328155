"""The gate's count of a client's subscriptions from the WebSocket frames it passes on:
for generated sessions (subscribes and unsubscribes of random ids, binary frames between
them, text messages fragmented, frames of every length encoding, the bytes cut anywhere),
the count is the model's and the client is named over its cap exactly when the model is,
and the bytes read end between two messages exactly where one ended;
and through the gate, a client that subscribes to one channel too many is closed with 1008."""

from __future__ import annotations

import asyncio
import json
import os
import random

import pytest

from mapservice.api.foxglove_frames import MAX_MESSAGE_BYTES, SubscriptionCount
from tests.api.test_foxglove_gate import Upstream101, gate_over, request, settings


def frame(opcode: int, payload: bytes, fin: bool = True) -> bytes:
    """A client's (masked) frame."""
    head = bytes([(0x80 if fin else 0) | opcode])
    n = len(payload)
    if n < 126:
        head += bytes([0x80 | n])
    elif n < 65536:
        head += bytes([0x80 | 126]) + n.to_bytes(2, "big")
    else:
        head += bytes([0x80 | 127]) + n.to_bytes(8, "big")
    mask = os.urandom(4)
    return head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))


def text_frames(message: dict, rng: random.Random) -> list[bytes]:
    data = json.dumps(message).encode()
    if rng.random() < 0.3 and len(data) > 2:  # fragmented
        cut = rng.randrange(1, len(data))
        return [frame(0x1, data[:cut], fin=False), frame(0x0, data[cut:])]
    return [frame(0x1, data)]


@pytest.mark.parametrize("seed", range(20))
def test_the_count_is_the_models_however_the_bytes_come(seed):
    rng = random.Random(seed)
    cap = rng.randrange(1, 40)
    count = SubscriptionCount(cap)
    model: set[int] = set()
    stream = b""
    over_at = None  # the message after which the model is over the cap
    messages = 0
    ends = {0}  # the offsets at which a message ends (a frame of the gate's may go)
    frame_ends = [0]  # and at which a frame does (cut there often)

    def add(frames: list[bytes]) -> None:
        nonlocal stream
        for f in frames:
            stream += f
            frame_ends.append(len(stream))
        ends.add(len(stream))

    while messages < 60 and over_at is None:
        if rng.random() < 0.2:
            payload = os.urandom(rng.choice((10, 200, 70_000)))
            if rng.random() < 0.3:  # fragmented, with a ping between the fragments
                add([frame(0x2, payload[:5], fin=False), frame(0x9, b"p"), frame(0x0, payload[5:])])
            else:
                add([frame(0x2, payload)])  # binary: skipped
            continue
        if rng.random() < 0.6 or not model:
            ids = [rng.randrange(200) for _ in range(rng.randrange(1, 6))]
            message = {"op": "subscribe", "subscriptions": [{"id": i, "channelId": i} for i in ids]}
            model |= set(ids)
        else:
            ids = rng.sample(sorted(model), rng.randrange(1, len(model) + 1))
            message = {"op": "unsubscribe", "subscriptionIds": ids}
            model -= set(ids)
        add(text_frames(message, rng))
        messages += 1
        if len(model) > cap:
            over_at = len(stream)
    said = None
    fed = 0
    while fed < len(stream) and said is None:
        n = rng.randrange(1, 5000)
        if rng.random() < 0.5:  # to the end of a frame
            n = next(end for end in frame_ends if end > fed) - fed
        said = count.feed(stream[fed : fed + n])
        fed += n
        assert said is not None or count.at_boundary == (min(fed, len(stream)) in ends)
    if over_at is None:
        assert said is None and count.subscriptions.keys() == model
    else:
        assert said is not None and "MAPSERVICE_FOXGLOVE_MAX_SUBSCRIPTIONS" in said
        assert fed >= over_at  # not before the message that went over


def test_unmasked_frames_and_huge_texts_are_refused():
    assert "masked" in SubscriptionCount(5).feed(bytes([0x81, 0x02]) + b"{}")
    huge = bytes([0x81, 0x80 | 127]) + (10**7).to_bytes(8, "big") + b"abcd"
    assert "over" in SubscriptionCount(5).feed(huge)


@pytest.mark.parametrize("opcode", [0x1, 0x2], ids=["text", "binary"])
@pytest.mark.parametrize("pieces", [1, 3, 40])
@pytest.mark.parametrize("extra", [0, 1, 10**7])
def test_a_message_over_the_limit_is_refused_however_it_is_cut(opcode, pieces, extra):
    """Text or binary (the SDK reads a binary message whole, up to 16 MiB, for requests of
    a few bytes: playback control), in one frame or fragments, fed in any slices: refused
    as soon as its frames' headers say it is over MAX_MESSAGE_BYTES, before its payload;
    one at the limit passes. The headers alone are sent, with just enough payload."""
    size = MAX_MESSAGE_BYTES + extra
    cuts = sorted(random.Random(size * pieces).sample(range(1, size), pieces - 1))
    lengths = [b - a for a, b in zip([0, *cuts], [*cuts, size], strict=True)]
    count = SubscriptionCount(5)
    reason = None
    for i, length in enumerate(lengths):
        code = opcode if i == 0 else 0x0
        head = frame(code, b"", fin=i == len(lengths) - 1)
        head = head[:1] + _length_field(length) + head[2:]
        reason = count.feed(head)
        if reason:
            break
        payload = b"\x00" * length if opcode == 0x2 else b" " * length
        reason = count.feed(payload)  # what it unmasks to does not matter here
        if reason:
            break
    if extra:
        assert reason is not None and "over" in reason, reason
        assert str(MAX_MESSAGE_BYTES) in reason
    else:
        assert reason is None and count.at_boundary


def _length_field(n: int) -> bytes:
    """A masked frame's second byte and extended length for a payload of `n` bytes."""
    if n < 126:
        return bytes([0x80 | n])
    if n < 65536:
        return bytes([0x80 | 126]) + n.to_bytes(2, "big")
    return bytes([0x80 | 127]) + n.to_bytes(8, "big")


def test_control_frames_over_125_bytes_are_refused():
    """RFC 6455 allows 125; the gate passes a ping on unread, so it must not be larger."""
    assert SubscriptionCount(5).feed(frame(0x9, b"p" * 125)) is None
    assert "125" in SubscriptionCount(5).feed(frame(0x9, b"p" * 126))


def test_a_client_over_its_cap_is_closed_with_1008_through_the_gate():
    async def main() -> bytes:
        upstream = Upstream101(flood=False)
        gate, port = await gate_over(upstream, settings(foxglove_max_subscriptions=3))
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(request())
        await reader.readuntil(b"\r\n\r\n")
        for i in range(4):
            sub = {"op": "subscribe", "subscriptions": [{"id": i, "channelId": i}]}
            writer.write(frame(0x1, json.dumps(sub).encode()))
            await writer.drain()
        async with asyncio.timeout(5):
            answer = await reader.read()  # until the gate closes the connection
        writer.close()
        await gate.stop()
        return answer

    answer = asyncio.run(main())
    assert answer[:1] == b"\x88"  # a close frame, then the end of the connection
    assert answer[2:4] == (1008).to_bytes(2, "big") and b"MAX_SUBSCRIPTIONS" in answer
