"""The SDK's side of one Foxglove connection, read as the gate passes it on: a subscription
the SDK lost to its own race is sent again.

The SDK (0.30) advertises a channel made while a client is connected by queueing the
advertisement first and recording that the client has the channel second
(`ConnectedClient::advertise_channels`, rust/foxglove/src/websocket/connected_client.rs).
A client that subscribes as soon as the advertisement reaches it, while the thread that
made the channel has not yet recorded it (a loaded machine), is answered "Unknown channel
ID: N" (`ConnectedClient::on_subscribe`) and its subscription is dropped: the client never
asks again, so it never gets that channel. The SDK's answer is how the gate learns it: a
channel this client was advertised (and not unadvertised since) that the client holds a
subscription to is one the SDK records a moment later, so the gate swallows the answer and
sends the same subscription again, a little later each time (the thread recording it only
has to be scheduled), at most `MAX_ATTEMPTS` times; an answer after that goes on to the
client.

Server frames are never masked or, from this SDK, fragmented; binary frames (the data) pass
through as they come, their payload unread; a text frame is held until it is whole (a frame
over `MAX_HELD_BYTES` passes unread)."""

from __future__ import annotations

import json
from dataclasses import dataclass

from .foxglove_frames import SubscriptionCount, client_text_frame

_TEXT = 0x1
MAX_HELD_BYTES = 16 * 1024 * 1024  # an advertisement of thousands of channels with schemas
MAX_ATTEMPTS = 10
_FIRST_DELAY_S, _MAX_DELAY_S = 0.005, 0.5  # about two seconds over all attempts
_UNKNOWN_CHANNEL = "Unknown channel ID: "


@dataclass(frozen=True)
class Resubscribe:
    """One subscription to send the SDK again, after `delay_s`."""

    subscription_id: int
    channel_id: int
    delay_s: float

    def frame(self) -> bytes:
        """The client's subscribe message for it, as a (masked) client frame."""
        message = {
            "op": "subscribe",
            "subscriptions": [{"id": self.subscription_id, "channelId": self.channel_id}],
        }
        return client_text_frame(json.dumps(message, separators=(",", ":")).encode())


class ServerStream:
    """Feed it the SDK's bytes for one client in order (`feed`): the bytes to pass on and
    the subscriptions to send again (`client`: the same connection's client side)."""

    def __init__(self, client: SubscriptionCount) -> None:
        self.client = client
        self.advertised: set[int] = set()  # channel ids the client has been advertised
        self.attempts: dict[int, int] = {}  # subscription id -> times sent again
        self.resent = 0  # subscriptions sent again (tests, logs)
        self._held = bytearray()  # the start of a frame not passed on yet
        self._pass = 0  # bytes of the current frame's payload to pass on unread

    def feed(self, data: bytes) -> tuple[bytes, list[Resubscribe]]:
        if self._held:
            data, self._held = bytes(self._held) + data, bytearray()
        again: list[Resubscribe] = []
        swallowed: list[tuple[int, int]] = []  # the frames not passed on: (start, end)
        end = len(data)
        pos = min(self._pass, end)  # the rest of a frame passed on unread
        self._pass -= pos
        while pos < end:
            header = _header(data, pos)
            if header is None:  # cut within a frame's header: the rest comes with the next bytes
                break
            readable, size, length = header
            frame_end = pos + size + length
            if not readable or length > MAX_HELD_BYTES:
                if frame_end > end:
                    self._pass = frame_end - end
                    pos = end
                    break
            elif frame_end > end:  # a text frame is held until it is whole
                break
            else:
                resubscribe = self._read(data[pos + size : frame_end])
                if (
                    resubscribe is not None
                ):  # the SDK's answer swallowed: the subscription goes again
                    again.append(resubscribe)
                    swallowed.append((pos, frame_end))
            pos = frame_end
        if pos < end:
            self._held += data[pos:]
        if not swallowed:
            return (data if pos == end else data[:pos]), again
        kept, at = [], 0
        for cut_start, cut_end in swallowed:
            kept.append(data[at:cut_start])
            at = cut_end
        kept.append(data[at:pos])
        return b"".join(kept), again

    def _read(self, payload: bytes) -> Resubscribe | None:
        """Notes an (un)advertisement; for the SDK's "unknown channel" answer to a
        subscription it is about to record, that subscription to send again."""
        start = payload[:40]
        if b"advertise" not in start and b"status" not in start:
            return None  # the rest of the protocol's messages: nothing to note
        try:
            message = json.loads(payload)
        except ValueError:
            return None
        if not isinstance(message, dict):
            return None
        op = message.get("op")
        if op == "advertise":
            for channel in message.get("channels") or ():
                if isinstance(channel, dict) and isinstance(channel.get("id"), int):
                    self.advertised.add(channel["id"])
        elif op == "unadvertise":
            for channel_id in message.get("channelIds") or ():
                if isinstance(channel_id, int):
                    self.advertised.discard(channel_id)
        elif op == "status" and str(message.get("message", "")).startswith(_UNKNOWN_CHANNEL):
            return self._lost(str(message["message"])[len(_UNKNOWN_CHANNEL) :])
        return None

    def _lost(self, channel: str) -> Resubscribe | None:
        try:
            channel_id = int(channel)
        except ValueError:
            return None
        if channel_id not in self.advertised:
            return None  # never advertised, or gone: the client's mistake, it hears of it
        subscription = self.client.subscription_to(channel_id)
        if subscription is None:
            return None
        attempt = self.attempts.get(subscription, 0)
        if attempt >= MAX_ATTEMPTS:
            return None
        self.attempts[subscription] = attempt + 1
        self.resent += 1
        delay_s = min(_FIRST_DELAY_S * 2**attempt, _MAX_DELAY_S)
        return Resubscribe(subscription, channel_id, delay_s)


def _header(data: bytes, pos: int) -> tuple[bool, int, int] | None:
    """The frame at `pos`: whether it is a whole text frame whose payload can be read as
    it is (unmasked), the header's size and the payload's length; None if cut short."""
    if len(data) - pos < 2:
        return None
    first, second = data[pos], data[pos + 1]
    length, size = second & 0x7F, 2
    if length == 126:
        if len(data) - pos < 4:
            return None
        length, size = int.from_bytes(data[pos + 2 : pos + 4], "big"), 4
    elif length == 127:
        if len(data) - pos < 10:
            return None
        length, size = int.from_bytes(data[pos + 2 : pos + 10], "big"), 10
    masked = bool(second & 0x80)
    if masked:
        size += 4
    if len(data) - pos < size:
        return None
    readable = first == (0x80 | _TEXT) and not masked  # final, no extension bits
    return readable, size, length
