"""A Foxglove client's WebSocket frames, read as the gate passes them on unchanged: how many
channels it is subscribed to (the protocol's `subscribe` and `unsubscribe` text messages),
so that the gate can close a client that subscribes to more than its cap, and which channel
each subscription names (the gate sends one again that the SDK lost: foxglove_resubscribe.py).
Binary frames (playback control) are skipped, not buffered, but counted: a client's message
of either kind over `MAX_MESSAGE_BYTES` closes it as soon as its frames' headers say so
(the SDK would read a binary one whole, up to 16 MiB, for requests of a few bytes), as does
a control frame over the 125 bytes RFC 6455 allows."""

from __future__ import annotations

import json
import os

_TEXT, _CONTINUATION, _CONTROL = 0x1, 0x0, 0x8
MAX_MESSAGE_BYTES = 1024 * 1024  # a subscribe to thousands of channels is well below
_MAX_CONTROL_BYTES = 125


class SubscriptionCount:
    """Feed it the client's bytes in order; `feed` says why to close the client, or None."""

    def __init__(self, cap: int) -> None:
        self.cap = cap
        self.subscriptions: dict[int, int] = {}  # subscription id -> channel id
        self._buf = bytearray()
        self._skip = 0  # bytes of a frame not read (binary)
        self._text = bytearray()  # a text message's fragments so far
        self._in_text = False
        self._in_message = False  # between the fragments of a message (text or binary)
        self._binary = 0  # bytes of the binary message so far

    @property
    def at_boundary(self) -> bool:
        """Whether the bytes fed so far end between two messages: a frame of the gate's own
        may go to the server here without cutting one of the client's."""
        return not (self._buf or self._skip or self._in_message)

    def subscription_to(self, channel_id: int) -> int | None:
        """The client's (latest) subscription to `channel_id`, if it holds one."""
        found = None
        for subscription, channel in self.subscriptions.items():
            if channel == channel_id:
                found = subscription
        return found

    def feed(self, data: bytes) -> str | None:
        if self._skip:
            taken = min(self._skip, len(data))
            self._skip -= taken
            data = data[taken:]
        self._buf += data
        while True:
            frame = self._next_frame()
            if frame is None:
                return None
            if isinstance(frame, str):
                return frame
            fin, opcode, payload = frame
            if opcode < _CONTROL:  # control frames may come between a message's fragments
                self._in_message = not fin
            if opcode == _TEXT or (opcode == _CONTINUATION and self._in_text):
                self._text += payload
                self._in_text = not fin
                if len(self._text) > MAX_MESSAGE_BYTES:
                    return _too_large("text")
                if fin:
                    reason = self._message(bytes(self._text))
                    self._text.clear()
                    if reason:
                        return reason

    def _next_frame(self) -> tuple[bool, int, bytes] | str | None:
        buf = self._buf
        if len(buf) < 2:
            return None
        fin, opcode = bool(buf[0] & 0x80), buf[0] & 0x0F
        masked, length, at = bool(buf[1] & 0x80), buf[1] & 0x7F, 2
        if length == 126:
            if len(buf) < 4:
                return None
            length, at = int.from_bytes(buf[2:4], "big"), 4
        elif length == 127:
            if len(buf) < 10:
                return None
            length, at = int.from_bytes(buf[2:10], "big"), 10
        if not masked:
            return "a client's frames must be masked (RFC 6455)"
        if len(buf) < at + 4:
            return None
        mask, at = bytes(buf[at : at + 4]), at + 4
        is_text = opcode == _TEXT or (opcode == _CONTINUATION and self._in_text)
        if opcode >= _CONTROL and length > _MAX_CONTROL_BYTES:
            return f"a control frame over {_MAX_CONTROL_BYTES} bytes (RFC 6455)"
        if not is_text and opcode < _CONTROL:
            self._binary += length
            if self._binary > MAX_MESSAGE_BYTES:
                return _too_large("binary")
            if fin:
                self._binary = 0
        if not is_text:  # skipped as it streams by
            available = len(buf) - at
            if available >= length:
                del buf[: at + length]
            else:
                self._skip = length - available
                buf.clear()
            return (fin, opcode, b"")
        if length > MAX_MESSAGE_BYTES:
            return _too_large("text")
        if len(buf) < at + length:
            return None
        payload = bytes(buf[at : at + length])
        del buf[: at + length]
        return (fin, opcode, _mask(payload, mask))

    def _message(self, text: bytes) -> str | None:
        try:
            message = json.loads(text)
        except ValueError:
            return None  # the server answers what it cannot read; nothing to count
        if not isinstance(message, dict):
            return None
        if message.get("op") == "subscribe":
            for s in message.get("subscriptions") or ():
                if isinstance(s, dict) and isinstance(s.get("id"), int):
                    channel = s.get("channelId")
                    self.subscriptions[s["id"]] = channel if isinstance(channel, int) else -1
        elif message.get("op") == "unsubscribe":
            for i in message.get("subscriptionIds") or ():
                if isinstance(i, int):
                    self.subscriptions.pop(i, None)
        if len(self.subscriptions) > self.cap:
            return (
                f"more than {self.cap} subscriptions "
                "(MAPSERVICE_FOXGLOVE_MAX_SUBSCRIPTIONS); subscribe to fewer channels"
            )
        return None


def _too_large(kind: str) -> str:
    return f"a {kind} message over {MAX_MESSAGE_BYTES} bytes"


def close_frame(code: int, reason: str) -> bytes:
    """A server's (unmasked) close frame with `code` and `reason` (cut to fit 125 bytes)."""
    body = code.to_bytes(2, "big") + reason.encode()[:123]
    return bytes([0x88, len(body)]) + body


def client_text_frame(text: bytes) -> bytes:
    """A client's (masked) text frame of `text`, as the server must be sent one."""
    n = len(text)
    if n < 126:
        head = bytes([0x81, 0x80 | n])
    elif n < 65536:
        head = bytes([0x81, 0x80 | 126]) + n.to_bytes(2, "big")
    else:
        head = bytes([0x81, 0x80 | 127]) + n.to_bytes(8, "big")
    mask = os.urandom(4)
    return head + mask + _mask(text, mask)


def _mask(data: bytes, key: bytes) -> bytes:
    """`data` XOR the 4-byte `key` repeated (RFC 6455 masking; unmasking is the same)."""
    keys = (key * (len(data) // 4 + 1))[: len(data)]
    return (int.from_bytes(data, "big") ^ int.from_bytes(keys, "big")).to_bytes(len(data), "big")
