"""The Foxglove channels' picture, on the memory store with generated histories: a seek to
any instant draws the floor pixel for pixel as the API's map image at that instant, and
every robot as /api/v1/robots?at= lists it; playing a span sends every chunk write and pose
of it in event-time order however many fall on one instant or one page; the live feed's
messages move the picture as the store's rows do; a client that subscribes late gets the
current message again."""

from __future__ import annotations

import random
import time
from typing import Any

import numpy as np
import pytest

from api.foxglove_gate import SDK_SUBPROTOCOL
from mapservice.adapters.foxglove_messages import (
    pose_row_of_live,
    window_changes,
    window_poses,
)
from mapservice.adapters.foxglove_replay import ReplaySession
from mapservice.adapters.foxglove_scene import FoxgloveScene
from mapservice.adapters.mcap_channels import (
    MAP_CHANGES_TOPIC,
    MAP_TOPIC,
    TF_TOPIC,
    path_topic,
    pose_topic,
    state_topic,
)
from mapservice.adapters.mcap_export import ReplaySources
from mapservice.core.live_messages import live_record_texts, live_records
from mapservice.core.render import stitch
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import chunk_event, meta_event, pose_event

T0 = 1_795_255_200_000


class Recorder:
    """FoxgloveChannels' interface, keeping (topic, log time, message) in order."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, int, Any]] = []
        self.clients = True  # whether a client listens (to every channel)

    def declare_protobuf(self, topic: str, message_class: Any) -> None:
        pass

    def declare_json(self, topic: str, schema_name: str) -> None:
        pass

    def listened(self, topic: str) -> bool:
        return self.clients

    def any_listened(self) -> bool:
        return self.clients

    def protobuf(self, topic: str, message: Any, ts_ms: int) -> None:
        self.sent.append((topic, ts_ms, message))

    def json(self, topic: str, schema_name: str, doc: dict, ts_ms: int) -> None:
        self.sent.append((topic, ts_ms, doc))

    def on(self, topic: str) -> list[tuple[int, Any]]:
        return [(t, m) for top, t, m in self.sent if top == topic]


def history(seed: int) -> tuple[MemoryStore, list]:
    """A floor of 4 x 5 chunks and three robots over ten minutes: random writes (some at
    one instant) and poses with and without planned paths."""
    rng = random.Random(seed)
    store = MemoryStore()
    events = [meta_event(T0)]
    for _ in range(rng.randrange(20, 60)):
        t = T0 + rng.randrange(1, 600_000) // 1000 * 1000  # whole seconds: instants shared
        pixels = bytes([rng.choice((0, 100, 254))]) * 10_000
        events.append(
            chunk_event(f"r{rng.randrange(3)}", t, rng.randrange(4), rng.randrange(5), pixels)
        )
    for robot in ("r0", "r1", "r2"):
        for t in range(T0 + rng.randrange(5_000), T0 + 600_000, 3_000):
            # In millimetres, as the store keeps them (the live stream sends them as reported).
            path = [
                (round(rng.uniform(0, 20), 3), round(rng.uniform(0, 20), 3))
                for _ in range(rng.randrange(3))
            ]
            events.append(
                pose_event(
                    robot,
                    t,
                    round(rng.uniform(0, 25), 3),
                    round(rng.uniform(0, 20), 3),
                    battery_level=rng.randrange(400) / 4,  # exact in float32, as stored
                    charging=rng.random() < 0.3,
                    loaded=rng.random() < 0.5,
                    path=path or None,
                )
            )
    store.append(events)
    return store, events


def sources(store: MemoryStore) -> ReplaySources:
    return ReplaySources(store, store, store, store, store, store)


def grid_pixels(grid: Any) -> np.ndarray:
    rows = len(grid.data) // grid.row_stride
    return np.flipud(np.frombuffer(grid.data, dtype=np.uint8).reshape(rows, grid.row_stride))


@pytest.mark.parametrize("seed", range(6))
def test_a_seek_draws_the_floor_and_robots_as_the_api_reads_them(seed):
    store, _ = history(seed)
    rng = random.Random(seed)
    channels = Recorder()
    scene = FoxgloveScene(channels, sources(store))  # type: ignore[arg-type]
    for at in sorted(T0 + rng.randrange(-1_000, 610_000) for _ in range(4)):
        channels.sent.clear()
        scene.draw_at(at)
        meta = store.latest_meta()
        chunks = store.map_at(at)
        expected = stitch(
            meta, chunks, store.chunk_contents([bytes.fromhex(c.content_hash) for c in chunks])
        )
        [(t, grid)] = channels.on(MAP_TOPIC)
        assert t == at and np.array_equal(grid_pixels(grid), expected)
        robots = store.robots_at(at)
        assert {top for top, _, _ in channels.sent if top.endswith("/pose")} == {
            pose_topic(r.robot_id) for r in robots
        }
        for r in robots:
            [(t, pose)] = channels.on(pose_topic(r.robot_id))
            p = pose.pose.position
            assert (t, p.x, p.y, p.z) == (r.ts_ms, r.x, r.y, r.z)
            [(_, state)] = channels.on(state_topic(r.robot_id))
            assert (state["battery_level"], state["charging"], state["loaded"]) == (
                r.battery_level,
                r.charging,
                r.loaded,
            )
            [(_, path)] = channels.on(path_topic(r.robot_id))  # at a seek, always
            assert [(q.position.x, q.position.y) for q in path.poses] == list(r.path or ())
        assert len(channels.on(TF_TOPIC)) == len(robots)


@pytest.mark.parametrize("seed", range(6))
def test_window_reads_take_every_row_across_pages_and_shared_instants(seed):
    store, _ = history(seed)
    rng = random.Random(seed)
    a = T0 + rng.randrange(0, 300_000)
    b = a + rng.randrange(1, 300_000)
    page = rng.randrange(1, 5)
    assert window_changes(store, a, b, page) == store.chunk_events(a, b, 1_000_000)
    assert list(window_poses(store, a, b, page)) == store.poses(a, b, None, 1_000_000)


@pytest.mark.parametrize("seed", range(6))
def test_playing_sends_every_write_and_pose_in_order_and_the_floor_as_at_the_end(seed):
    """A replay step of any length (a high speed is a long step) sends each chunk write of
    it once, in event-time order, writes before the poses of their instant, and the floor
    it ends with is the map at the step's end."""
    store, _ = history(seed)
    rng = random.Random(seed)
    session = ReplaySession(sources(store), T0, T0 + 600_000)
    channels = Recorder()
    scene = FoxgloveScene(channels, sources(store))  # type: ignore[arg-type]
    at = T0 + rng.randrange(0, 100_000)
    scene.draw_at(at)
    cursor = at
    while cursor < T0 + 600_000:
        step = rng.choice((100, 1_000, 6_000, 60_000, 250_000))
        channels.sent.clear()
        end = min(cursor + step, T0 + 600_000)
        session._play(scene, cursor, end)
        changes = [m for t, m in channels.on(MAP_CHANGES_TOPIC)]
        expected = store.chunk_events(cursor, end, 1_000_000)
        assert [
            (c["row"], c["column"], c["robot_id"], c["content_hash"], c["ts_ms"]) for c in changes
        ] == [(e.row, e.column, e.robot_id, e.content_hash, e.ts_ms) for e in expected]
        times = [
            t for top, t, _ in channels.sent if top in (MAP_CHANGES_TOPIC,) or top.endswith("/pose")
        ]
        assert times == sorted(times)
        poses = [(top, t) for top, t, _ in channels.sent if top.endswith("/pose")]
        assert poses == [
            (pose_topic(p.robot_id), p.ts_ms) for p in store.poses(cursor, end, None, 1_000_000)
        ]
        if expected:
            [(t, grid)] = channels.on(MAP_TOPIC)
            assert t == end - 1
            chunks = store.map_at(end - 1)
            meta = store.latest_meta()
            assert np.array_equal(
                grid_pixels(grid),
                stitch(
                    meta,
                    chunks,
                    store.chunk_contents([bytes.fromhex(c.content_hash) for c in chunks]),
                ),
            )
        cursor = end


def test_live_messages_move_the_picture_as_the_stored_rows_do():
    """The live stream's pose and chunk messages (as the relay hands them on) give the same
    messages as the store's rows of the same events; a late subscriber gets them again."""
    store, events = history(7)
    live = [text for record in live_records(events) for text in live_record_texts(record)]
    poses = [m for m in live if m["type"] == "pose"]
    by_key = {(r.robot_id, r.ts_ms): r for r in store.poses(T0, T0 + 700_000, None, 1_000_000)}
    for m in poses:
        row = pose_row_of_live(m)
        stored = by_key[(row.robot_id, row.ts_ms)]
        assert (
            row.x,
            row.y,
            row.z,
            row.qw,
            row.battery_level,
            row.charging,
            row.loaded,
            row.path,
        ) == (
            stored.x,
            stored.y,
            stored.z,
            stored.qw,
            stored.battery_level,
            stored.charging,
            stored.loaded,
            stored.path,
        )
    channels = Recorder()
    scene = FoxgloveScene(channels, sources(store))  # type: ignore[arg-type]
    scene.draw_at(T0 + 300_000)
    channels.sent.clear()
    scene.resend(MAP_TOPIC)
    scene.resend(pose_topic("r1"))
    [(t, grid)] = channels.on(MAP_TOPIC)
    chunks = store.map_at(T0 + 300_000)
    expected = stitch(
        store.latest_meta(),
        chunks,
        store.chunk_contents([bytes.fromhex(c.content_hash) for c in chunks]),
    )
    assert t == T0 + 300_000 and np.array_equal(grid_pixels(grid), expected)
    [(t, _)] = channels.on(pose_topic("r1"))
    assert t == store.robots_at(T0 + 300_000)[1].ts_ms
    assert [top for top, _, _ in channels.sent] == [MAP_TOPIC, pose_topic("r1")]


@pytest.mark.parametrize("seed", range(4))
def test_the_live_feed_sends_each_write_and_pose_of_the_stream_and_the_floor_they_make(seed):
    """FoxgloveLive over the live stream's messages of a history (in batches of any size):
    every chunk write on /map/changes and every pose, in the stream's order, and the last
    floor sent is the map after them all."""
    from mapservice.adapters.foxglove_live import FoxgloveLive

    store, events = history(seed)
    ordered = sorted(events[1:], key=lambda e: (e.event_time_ms, e.robot_id))
    live = [text for record in live_records(ordered) for text in live_record_texts(record)]
    channels = Recorder()
    scene = FoxgloveScene(channels, sources(store))  # type: ignore[arg-type]
    feed = FoxgloveLive(scene, lambda: T0 - 1, grid_every_s=1e-9, annotations_every_s=3600)
    try:
        feed._draw_now()
        rng = random.Random(seed)
        i = 0
        while i < len(live):
            n = rng.randrange(1, 40)
            feed._apply(live[i : i + n])
            i += n
    finally:
        feed.close()
    changes = [m for _, m in channels.on(MAP_CHANGES_TOPIC)]
    assert [(c["row"], c["column"], c["robot_id"], c["ts_ms"]) for c in changes] == [
        (m["row"], m["column"], m["robotId"], m["ts_ms"]) for m in live if m["type"] == "chunk"
    ]
    assert [(top, t) for top, t, _ in channels.sent if top.endswith("/pose")] == [
        (pose_topic(m["robotId"]), m["ts_ms"]) for m in live if m["type"] == "pose"
    ]
    end = T0 + 700_000
    chunks = store.map_at(end)
    expected = stitch(
        store.latest_meta(),
        chunks,
        store.chunk_contents([bytes.fromhex(c.content_hash) for c in chunks]),
    )
    assert np.array_equal(grid_pixels(channels.on(MAP_TOPIC)[-1][1]), expected)


@pytest.mark.parametrize("sink", [False, True], ids=["nobody-listens", "a-sink-listens"])
def test_the_live_feed_builds_messages_only_for_a_channel_someone_takes(
    sink, tmp_path, monkeypatch
):
    """On the SDK's own channels: with no client (no sink) the live stream moves the scene
    (its robots, its floor) but builds no message and draws no write into the floor (no
    chunk read or decompressed) until the floor is looked at; with a sink (an MCAP writer
    on the same context, as a client's subscription is one) every pose, transform, state
    and write is sent, and the floor."""
    import foxglove

    from mapservice.adapters import foxglove_scene
    from mapservice.adapters.foxglove_channels import FoxgloveChannels
    from mapservice.adapters.foxglove_live import FoxgloveLive

    built: list[str] = []
    for name in ("pose_message", "transform_message", "path_message", "state_doc"):
        real = getattr(foxglove_scene, name)
        monkeypatch.setattr(
            foxglove_scene, name, lambda row, real=real, name=name: built.append(name) or real(row)
        )
    store, events = history(1)
    ordered = sorted(events[1:], key=lambda e: (e.event_time_ms, e.robot_id))
    live = [text for record in live_records(ordered) for text in live_record_texts(record)]
    context = foxglove.Context()
    writer = foxglove.open_mcap(tmp_path / "sink.mcap", context=context) if sink else None
    channels = FoxgloveChannels(context)
    scene = FoxgloveScene(channels, sources(store))
    feed = FoxgloveLive(scene, lambda: T0 - 1, grid_every_s=1e-9, annotations_every_s=3600)
    try:
        feed._draw_now()
        built.clear()
        read = store.chunk_contents
        reads: list[int] = []
        monkeypatch.setattr(
            store, "chunk_contents", lambda hashes: reads.append(len(hashes)) or read(hashes)
        )
        feed._apply(live)
    finally:
        feed.close()
        if writer is not None:
            writer.close()
    poses = sum(m["type"] == "pose" for m in live)
    assert poses > 10
    assert {m["robotId"] for m in live if m["type"] == "pose"} == set(scene.robots)
    assert scene.floor is not None and scene.floor_ms == max(
        m["ts_ms"] for m in live if m["type"] == "chunk"
    )
    if sink:
        assert built.count("pose_message") == built.count("state_doc") == poses
        assert built.count("transform_message") == poses
        assert not scene.floor_dirty  # the floor went out
    else:
        assert built == [] and reads == []
        assert scene.floor_dirty  # kept for a client that subscribes: `resend` draws it
    chunks = store.map_at(T0 + 700_000)
    expected = stitch(
        store.latest_meta(), chunks, read([bytes.fromhex(c.content_hash) for c in chunks])
    )
    assert np.array_equal(scene.floor.pixels, expected)


class _Channel:
    def __init__(self, topic: str) -> None:
        self.topic = topic


def _wait_until(done, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not done():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def test_a_replay_session_draws_its_first_picture_once_its_client_subscribed():
    """Not as its server starts: robot channels made while the client is still being
    connected were advertised and subscribed but never sent in about one session of
    seven (`mapservice bench foxglove` found it: a robot missing from every frame)."""
    store, _ = history(1)
    session = ReplaySession(sources(store), T0, T0 + 600_000)
    session.start()
    try:
        assert session.scene is not None
        time.sleep(0.3)  # the player runs: it would have drawn by now
        assert session.scene.robots == {} and session.scene.floor is None
        session.on_subscribe(None, _Channel(MAP_TOPIC))
        assert _wait_until(lambda: session.scene is not None and session.scene.robots != {})
        assert session.scene.floor_ms == T0 + 600_000
    finally:
        session.stop()


def test_a_replay_session_advertises_every_robot_of_its_window_when_its_client_connects():
    """Before the client subscribes to anything: the SDK advertises a channel made while a
    client is connected before it records that advertisement, so a client quick to
    subscribe was told "unknown channel" and never got that robot (on a loaded machine,
    `mapservice bench foxglove` missed one robot in every seek). The first advertisement,
    made as the client connects, is one its subscriptions cannot overtake."""
    import json

    from websockets.sync.client import connect

    store, _ = history(2)
    session = ReplaySession(sources(store), T0, T0 + 600_000)
    port = session.start()
    try:
        # The SDK's own subprotocol (the API's gate offers clients the older name too).
        with connect(f"ws://127.0.0.1:{port}", subprotocols=[SDK_SUBPROTOCOL]) as ws:
            advertised: set[str] = set()
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:
                try:
                    message = ws.recv(timeout=0.2)
                except TimeoutError:
                    continue
                if isinstance(message, str) and (doc := json.loads(message))["op"] == "advertise":
                    advertised |= {c["topic"] for c in doc["channels"]}
            robots = {r.robot_id for r in store.robots_at(T0 + 600_000)}
            assert robots == {"r0", "r1", "r2"}
            for robot in robots:
                assert {pose_topic(robot), path_topic(robot), state_topic(robot)} <= advertised
            assert session.scene is not None and session.scene.robots == {}  # nothing drawn yet
    finally:
        session.stop()


class _SlowReplay(ReplaySession):
    """A session whose every window read takes `read_s` (a loaded machine), recording them."""

    read_s = 0.3

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self.windows: list[tuple[int, int]] = []

    def _play(self, scene: FoxgloveScene, from_ms: int, to_ms: int) -> None:
        time.sleep(self.read_s)
        self.windows.append((from_ms, to_ms))
        super()._play(scene, from_ms, to_ms)


@pytest.mark.parametrize("read_s", [0.0, 0.3])
def test_playing_keeps_its_speed_when_reads_are_slow_and_skips_no_window(read_s):
    """At 60x for 2 s, a player whose every read takes 0.3 s still covers about two minutes
    (its windows grow; they used to stay 6 s each and the playback ran at 15x), and the
    windows it played follow each other without a gap."""
    from foxglove.websocket import PlaybackCommand

    store, _ = history(3)
    session = _SlowReplay(sources(store), T0, T0 + 3_600_000)
    session.read_s = read_s
    session.start()
    try:
        session.on_subscribe(None, _Channel(MAP_TOPIC))

        def control(command: Any, seek_ms: int | None = None) -> None:
            session.on_playback_control_request(
                type(
                    "Request",
                    (),
                    {
                        "playback_speed": 60.0,
                        "playback_command": command,
                        "seek_time": None if seek_ms is None else seek_ms * 1_000_000,
                        "request_id": "r",
                    },
                )()
            )

        control(PlaybackCommand.Pause, T0)
        assert _wait_until(lambda: session.scene is not None and session.scene.floor_ms == T0)
        control(PlaybackCommand.Play)
        time.sleep(2.0)
        control(PlaybackCommand.Pause)
        # What was played (sent) by then: the window being read at the pause went out too,
        # though the playhead stays at its start (whether a read was in flight at the
        # pause is a matter of phase).
        time.sleep(read_s + 0.2)
        windows = [w for w in session.windows if w[0] >= T0]
        played = windows[-1][1] - T0
        assert played >= 0.75 * 2.0 * 60 * 1000, played
        assert windows[0][0] == T0
        assert all(a[1] == b[0] for a, b in zip(windows, windows[1:], strict=False)), windows
    finally:
        session.stop()
