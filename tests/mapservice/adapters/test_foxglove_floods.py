"""What a Foxglove client can make the server do, through the protocol itself (the SDK's
own servers, a WebSocket client): every message that costs the server work (a subscribe
re-sends its channel's current message, live to every client of the channel; a seek draws
the whole picture at T from the store; a speed sets how much history each playback step
reads) costs bounded work however many are sent and whatever number they carry, and the
server still does what the client asked last."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import struct
from collections import Counter
from collections.abc import AsyncIterator
from typing import Any

import pytest

from mapservice.adapters.foxglove_replay import MAX_TICK_WINDOWS, TICK_S, ReplaySession
from mapservice.adapters.foxglove_resends import RESEND_EVERY_S
from mapservice.adapters.foxglove_scene import FoxgloveScene
from mapservice.adapters.mcap_annotations import ANNOTATIONS_TOPIC
from mapservice.adapters.mcap_channels import MAP_TOPIC, TF_TOPIC, pose_topic, state_topic
from tests.api.test_foxglove_resubscribe import foxglove_client
from tests.mapservice.adapters.test_foxglove_scene import T0, history, sources

_NS_PER_MS = 1_000_000
FLOOD = 300  # messages of one kind in one burst (a few kB: one client's second)
_PLAY, _PAUSE = 0, 1


def playback_request(command: int, speed: float, seek_ms: int | None, request_id: str) -> bytes:
    """The protocol's binary playback control request (client opcode 3)."""
    rid = request_id.encode()
    seek_ns = 0 if seek_ms is None else seek_ms * _NS_PER_MS
    return struct.pack("<BBfBQI", 3, command, speed, seek_ms is not None, seek_ns, len(rid)) + rid


def playback_state(message: bytes) -> tuple[float, int, str] | None:
    """(speed, current time in ms, request id) of the server's playback state (opcode 5)."""
    if message[0] != 5:
        return None
    current_ns, speed = struct.unpack_from("<Qf", message, 2)
    (rid_length,) = struct.unpack_from("<I", message, 15)
    return speed, current_ns // _NS_PER_MS, message[19 : 19 + rid_length].decode()


class Spy:
    """Counts the scene's re-sends (by topic) and draws (by instant), in every server."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.resent: Counter[str] = Counter()
        self.drawn: list[int] = []
        resend, draw_at = FoxgloveScene.resend, FoxgloveScene.draw_at

        def counted_resend(scene: FoxgloveScene, topic: str) -> None:
            self.resent[topic] += 1
            resend(scene, topic)

        def counted_draw(scene: FoxgloveScene, at_ms: int) -> None:
            self.drawn.append(at_ms)
            draw_at(scene, at_ms)

        monkeypatch.setattr(FoxgloveScene, "resend", counted_resend)
        monkeypatch.setattr(FoxgloveScene, "draw_at", counted_draw)


@contextlib.asynccontextmanager
async def live_server() -> AsyncIterator[tuple[int, asyncio.Queue]]:
    """The live server on a generated history (`history(3)`, now at its end), its feed
    running: its port and the feed's queue of live messages."""
    import foxglove

    from mapservice.adapters.foxglove_channels import FoxgloveChannels
    from mapservice.adapters.foxglove_live import FoxgloveLive

    store, _ = history(3)
    context = foxglove.Context()
    scene = FoxgloveScene(FoxgloveChannels(context), sources(store))
    live = FoxgloveLive(scene, lambda: T0 + 600_000, grid_every_s=3600, annotations_every_s=3600)
    server = foxglove.start_server(
        name="live", host="127.0.0.1", port=0, context=context, server_listener=live
    )
    queue: asyncio.Queue = asyncio.Queue()
    feed = asyncio.ensure_future(live.run(queue))
    try:
        yield server.port, queue
    finally:
        feed.cancel()
        with contextlib.suppress(BaseException):
            await feed
        server.stop()
        live.close()


@contextlib.asynccontextmanager
async def replay_server(max_speed: float = 3600.0) -> AsyncIterator[ReplaySession]:
    store, _ = history(3)
    session = ReplaySession(sources(store), T0, T0 + 6 * 3_600_000, max_speed=max_speed)
    await asyncio.get_running_loop().run_in_executor(None, session.start)
    try:
        yield session
    finally:
        await asyncio.get_running_loop().run_in_executor(None, session.stop)


async def channel_of(ws: Any, topic: str) -> int:
    """The channel id of `topic`, from the server's advertisements."""
    topics: dict[str, int] = {}
    async with asyncio.timeout(10):
        while topic not in topics:
            message = await ws.recv()
            if isinstance(message, str) and (doc := json.loads(message))["op"] == "advertise":
                topics |= {c["topic"]: c["id"] for c in doc["channels"]}
    return topics[topic]


async def collect(ws: Any, seconds: float) -> list[Any]:
    """Every message the client gets within `seconds`."""
    got: list[Any] = []
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(seconds):
            while True:
                got.append(await ws.recv())
    return got


def data_for(messages: list[Any], subscription: int) -> int:
    """How many of `messages` are data (opcode 1) of `subscription`."""
    return sum(
        isinstance(m, bytes) and m[0] == 1 and struct.unpack_from("<I", m, 1)[0] == subscription
        for m in messages
    )


SUBSCRIBED_TOPICS = [MAP_TOPIC, TF_TOPIC, ANNOTATIONS_TOPIC, pose_topic("r1"), state_topic("r2")]


@pytest.mark.parametrize("server", ["live", "replay"])
@pytest.mark.parametrize("topic", SUBSCRIBED_TOPICS)
def test_a_flood_of_subscribes_resends_a_channel_once_a_second_and_the_last_gets_it(
    server, topic, monkeypatch
):
    """A client subscribes and unsubscribes `FLOOD` times in a burst (each subscribe used
    to re-send the channel's current message: live, the whole floor to every client of
    /map for each one), then once more and stays: the channel is re-sent at most once a
    second meanwhile, another client of it gets no more than that, and the last
    subscription gets its current message."""
    spy = Spy(monkeypatch)

    async def main() -> tuple[int, int, int]:
        async with contextlib.AsyncExitStack() as stack:
            if server == "live":
                port, _ = await stack.enter_async_context(live_server())
            else:
                port = (await stack.enter_async_context(replay_server())).server.port
            url = f"ws://127.0.0.1:{port}"
            ws = await stack.enter_async_context(foxglove_client(url))
            channel = await channel_of(ws, topic)
            other = None
            if server == "live":  # a second client of the same channel, live
                other = await stack.enter_async_context(foxglove_client(url))
                await channel_of(other, topic)
                await other.send(_subscribe(1, channel))
                await collect(other, 0.5)
            await ws.send(_subscribe(0, channel))  # the replay's first picture comes with it
            await collect(ws, 0.5)
            await ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": [0]}))
            spy.resent.clear()
            for i in range(1, FLOOD + 1):
                await ws.send(_subscribe(i, channel))
                await ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": [i]}))
            last = FLOOD + 1
            await ws.send(_subscribe(last, channel))
            others = asyncio.ensure_future(collect(other, 2.5)) if other else None
            got = await collect(ws, 2.5)
            to_other = data_for(await others, 1) if others else 0
            return spy.resent[topic], data_for(got, last), to_other

    resent, to_last, to_other = asyncio.run(main())
    most = math.ceil(2.5 / RESEND_EVERY_S) + 1
    assert 1 <= resent <= most, resent
    assert to_last >= 1  # the subscription that stayed got the channel's message
    assert to_other <= most * 3, to_other  # (/tf: one message per robot)


def _subscribe(subscription: int, channel: int) -> str:
    return json.dumps(
        {"op": "subscribe", "subscriptions": [{"id": subscription, "channelId": channel}]}
    )


def test_a_flood_of_seeks_draws_the_latest_not_each(monkeypatch):
    """`FLOOD` seeks in a burst (the app's slider dragged, or a client sending them on
    purpose): each used to queue its own draw of the whole picture from the store; the
    player draws the latest one (and at most a few on the way), and answers each."""
    spy = Spy(monkeypatch)

    async def main() -> tuple[ReplaySession, list[int], list[str]]:
        async with (
            replay_server() as session,
            foxglove_client(f"ws://127.0.0.1:{session.server.port}") as ws,
        ):
            await ws.send(_subscribe(0, await channel_of(ws, MAP_TOPIC)))
            await collect(ws, 0.5)
            spy.drawn.clear()
            for i in range(FLOOD):
                await ws.send(playback_request(_PAUSE, 1.0, T0 + i * 1000, f"s{i}"))
            got = await collect(ws, 2.5)
            answers = [s[2] for m in got if isinstance(m, bytes) and (s := playback_state(m))]
            return session, list(spy.drawn), answers

    session, drawn, answers = asyncio.run(main())
    assert answers == [f"s{i}" for i in range(FLOOD)]
    assert drawn and drawn[-1] == T0 + (FLOOD - 1) * 1000, drawn[-3:]
    assert len(drawn) <= FLOOD // 10, len(drawn)
    assert session.scene is not None and session.scene.floor_ms == drawn[-1]


# Every float32 the protocol can carry as a speed that is not a plain one.
SPEEDS = [math.nan, math.inf, -math.inf, 0.0, -1.0, 1e-45, 3.4e38, 1e9, 1000.0, 5.0]


@pytest.mark.parametrize("speed", SPEEDS, ids=str)
def test_any_requested_speed_plays_on_within_the_cap(speed):
    """Whatever speed a client asks for: an infinite one used to stop the player (each
    step failed, forever, while the state said Playing) and a huge one made one step read
    the whole window from the store. The speed is held to `max_speed` (the state the
    client gets says which), one that is no speed keeps the one before, and the player
    moves on in steps of at most `MAX_TICK_WINDOWS` ticks at that speed."""
    max_speed = 100.0
    windows: list[tuple[int, int]] = []

    async def main() -> tuple[ReplaySession, list[tuple[float, int, str]]]:
        async with (
            replay_server(max_speed) as session,
            foxglove_client(f"ws://127.0.0.1:{session.server.port}") as ws,
        ):
            play = session._play

            def recorded(scene: FoxgloveScene, from_ms: int, to_ms: int) -> None:
                windows.append((from_ms, to_ms))
                play(scene, from_ms, to_ms)

            session._play = recorded  # type: ignore[method-assign]
            await ws.send(_subscribe(0, await channel_of(ws, MAP_TOPIC)))
            await ws.send(playback_request(_PAUSE, 2.0, T0, "seek"))
            await collect(ws, 0.3)
            await ws.send(playback_request(_PLAY, speed, None, "play"))
            got = await collect(ws, 1.0)
            await ws.send(playback_request(_PAUSE, 1.0, None, "pause"))
            got += await collect(ws, 0.3)
            states = [s for m in got if isinstance(m, bytes) and (s := playback_state(m))]
            return session, states

    session, states = asyncio.run(main())
    expected = 2.0 if math.isnan(speed) or speed <= 0 else min(speed, max_speed)
    (answer,) = [s for s in states if s[2] == "play"]
    assert answer[0] == pytest.approx(expected, rel=1e-6)
    largest_ms = MAX_TICK_WINDOWS * TICK_S * 1000 * max_speed
    assert windows and all(b - a <= largest_ms for a, b in windows), windows
    assert session.playhead.at_ms > T0  # it played
