"""A believable past for the embedded demo: days of the shift simulator, fast-forwarded, stored.

A newcomer's `mapservice up` has minutes of history; replaying "two days ago" needs days.
This runs the same shift simulator the live demo runs (`robot/sim.py`: robots planning on
the map's free space, stations, chargers, pallets and doors changing the real map) over
the past `days`, and writes what its robots would have reported through the store code
the processors use: `HistoryStore.append` for the events, `record_conflicts` for the
conflicts, snapshots as the processors' timer builds them. History starts with the map
file itself at the first instant (what `mapservice map upload` writes), so the map at any
T is the real floor with that day's pallets and doors.

Fast-forward, and what it changes (so the whole week takes under a minute of CPU here,
simulation and inserts; BENCHMARKS.md has the figures):
- the simulation steps STEP_S seconds at a time; between steps each moving robot is
  advanced along its planned path, so poses lie on the path (on free pixels) every
  POSE_EVERY_S seconds instead of every second;
- the floor changes every CHANGE_EVERY_S on average instead of every 20 s;
- now and then a second robot reports a changed chunk a moment before the first, with a
  few pixels read differently (two robots' sensors disagreeing): a recorded conflict.
"""

from __future__ import annotations

import math
import random
import time
import zlib
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import structlog

from mapservice.adapters.ros_map import RosMap, meta_for, slice_chunks
from mapservice.core.change_feed import UPLOADER_ID
from mapservice.core.events import ChunkUpdated, Envelope, PoseReported, make_envelope
from mapservice.core.incident_model import IncidentThresholds
from mapservice.core.ports import HistoryStore, chunk_rows_of
from mapservice.core.retention import DAY_MS
from mapservice.core.wire2019 import content_hash
from mapservice.local.demo_incidents import store_incidents
from mapservice.processors.conflict_recorder import record_conflicts

log = structlog.get_logger(__name__)

STEP_S = 12
POSE_EVERY_S = 3
CHANGE_EVERY_S = 1800.0
CONFLICT_EVERY = (
    4  # the 1st, 5th, 9th ... changed chunk is also reported, differently, by another robot
)
UPLOAD_ROBOT_ID = UPLOADER_ID  # as `mapservice map upload` writes the map
BATCH_POSES = 100_000
SIMULATION_SHARE = 0.9  # of the progress shown; finding the incidents is the rest


@dataclass(frozen=True)
class BackfillResult:
    start_ms: int
    end_ms: int
    poses: int
    chunk_writes: int
    conflicts: int
    snapshots: int
    incidents: int
    seconds: float


def _chunk_event(
    robot_id: str,
    t_ms: int,
    row: int,
    column: int,
    pixels: bytes,
    width: int,
    height: int,
    lag_ms: int,
) -> Envelope:
    payload = ChunkUpdated(row, column, width, height, zlib.compress(pixels), content_hash(pixels))
    return make_envelope(robot_id, t_ms, t_ms + lag_ms, payload)


def _pose_event(
    robot_id: str,
    t_ms: int,
    xy: tuple[float, float],
    yaw: float,
    battery: float,
    charging: bool,
    loaded: bool,
    path,
    lag_ms: int,
) -> Envelope:
    q = (0.0, 0.0, round(math.sin(yaw / 2), 6), round(math.cos(yaw / 2), 6))
    payload = PoseReported(
        (xy[0], xy[1], 0.0), q, round(battery, 1), charging, loaded, tuple(path) if path else None
    )
    return make_envelope(robot_id, t_ms, t_ms + lag_ms, payload)


def map_events(ros_map: RosMap, t_ms: int) -> list[Envelope]:
    """The map file as history: its meta and every chunk, written at `t_ms`."""
    meta = meta_for(ros_map)
    events = [make_envelope(UPLOAD_ROBOT_ID, t_ms, t_ms, meta)]
    for (row, column), pixels in sorted(slice_chunks(ros_map).items()):
        events.append(
            _chunk_event(
                UPLOAD_ROBOT_ID, t_ms, row, column, pixels, meta.chunk_width, meta.chunk_height, 0
            )
        )
    return events


def _misread(pixels: bytes, rng: random.Random, unknown: int) -> bytes:
    """The chunk as a second robot's sensor saw it: a few pixels read as unknown."""
    out = bytearray(pixels)
    for _ in range(12):
        out[rng.randrange(len(out))] = unknown
    return bytes(out)


def simulate(
    ros_map: RosMap,
    robots: int,
    start_ms: int,
    end_ms: int,
    *,
    seed: int = 7,
    prefix: str = "sim",
    thresholds: IncidentThresholds | None = None,
) -> Iterator[tuple[int, list[Envelope]]]:
    """(simulated time reached, events) batches of the fast-forwarded shift, in time order;
    its robots' incidents (stalls, silences, late charges) sized against `thresholds`."""
    from mapservice.robot import sim
    from mapservice.robot.sim_incidents import for_incidents

    config = for_incidents(
        sim.SimConfig(dt_s=STEP_S, change_every_s=CHANGE_EVERY_S),
        thresholds or IncidentThresholds(),
    )
    state = sim.new_state(ros_map, robots, seed=seed, t_ms=start_ms, config=config, prefix=prefix)
    meta = state.meta
    rng = random.Random(f"{seed}:demo-history")
    speed_px = config.speed_m_s / ros_map.resolution
    batch: list[Envelope] = []
    tails: dict[str, tuple[tuple, tuple]] = {}  # robot -> (waypoints, them in metres)
    changed = 0

    def path(s, robot_id: str, here: tuple[float, float], waypoints) -> tuple:
        """The robot's path in metres (`here`, its position in metres, then its waypoints),
        converting each planned route once rather than at every pose."""
        wps = waypoints[: config.max_path_points - 1]
        if not wps:
            return ()
        # Driving only drops waypoints from the front: the current ones end the route.
        known = tails.get(robot_id)
        if known is None or len(wps) > len(known[0]) or known[0][len(known[0]) - len(wps) :] != wps:
            known = tails[robot_id] = (wps, tuple(sim.to_metres(s, p) for p in wps))
        return (here, *known[1][len(known[1]) - len(wps) :])

    while state.t_ms < end_ms:
        before = state
        state, out = sim.step(state)
        # Poses between the steps: each robot advanced along its own path (one standing
        # stands; one off the network reports nothing).
        for robot, after in zip(before.robots, state.robots, strict=True):
            if after.silent_s > 0:
                continue
            moves = after.pos != robot.pos
            for k in range(POSE_EVERY_S, STEP_S, POSE_EVERY_S):
                pos, yaw, passed = sim.advance_along(
                    robot.pos, robot.yaw, robot.waypoints, speed_px * k if moves else 0.0
                )
                here = sim.to_metres(before, pos)
                batch.append(
                    _pose_event(
                        robot.robot_id,
                        before.t_ms + k * 1000,
                        here,
                        yaw,
                        robot.battery,
                        robot.charging,
                        robot.loaded,
                        path(before, robot.robot_id, here, robot.waypoints[passed:]),
                        rng.randrange(15, 90),
                    )
                )
        for p in out.poses:
            batch.append(
                _pose_event(
                    p.robot_id,
                    p.t_ms,
                    (p.x, p.y),
                    p.yaw,
                    p.battery,
                    p.charging,
                    p.loaded,
                    p.path,
                    rng.randrange(15, 90),
                )
            )
        others = [r.robot_id for r in state.robots]
        for c in out.chunks:
            changed += 1
            batch.append(
                _chunk_event(
                    c.robot_id,
                    c.t_ms,
                    c.row,
                    c.column,
                    c.pixels,
                    meta.chunk_width,
                    meta.chunk_height,
                    rng.randrange(15, 90),
                )
            )
            second = [r for r in others if r != c.robot_id]
            if second and changed % CONFLICT_EVERY == 1:
                batch.append(
                    _chunk_event(
                        rng.choice(second),
                        c.t_ms - rng.randrange(1000, 5000),
                        c.row,
                        c.column,
                        _misread(c.pixels, rng, ros_map.unknown_value),
                        meta.chunk_width,
                        meta.chunk_height,
                        rng.randrange(15, 90),
                    )
                )
        if len(batch) >= BATCH_POSES:
            yield state.t_ms, batch
            batch = []
    if batch:
        yield state.t_ms, batch


def backfill(
    store: HistoryStore,
    ros_map: RosMap,
    *,
    days: float,
    robots: int,
    now_ms: int,
    conflict_window_ms: int,
    seed: int = 7,
    prefix: str = "sim",
    progress: Callable[[float], None] | None = None,
    thresholds: IncidentThresholds | None = None,
) -> BackfillResult:
    """Writes `days` of simulated history ending at `now_ms` into `store` (migrated), and
    the incidents the processors' rules (`thresholds`) find in it."""
    started = time.monotonic()
    th = thresholds or IncidentThresholds()
    start_ms = now_ms - int(days * DAY_MS)
    store.append(map_events(ros_map, start_ms))
    totals = {"poses": 0, "chunk_writes": 0, "conflicts": 0}

    def write(events: list[Envelope]) -> None:
        events.sort(key=lambda e: e.event_time_ms)
        if hasattr(store, "derive_views_between"):
            # The pose views from the stored rows, inside the engine: half the insert time.
            store.append_events(events)
            store.derive_views_between(events[0].event_time_ms, events[-1].event_time_ms)
        else:
            store.append(events)
        writes = chunk_rows_of(events)
        totals["chunk_writes"] += len(writes)
        totals["poses"] += len(events) - len(writes)
        totals["conflicts"] += record_conflicts(store, writes, conflict_window_ms)

    # The simulation (Python) and the inserts (mostly the engine) overlap: one batch is
    # stored while the next is simulated.
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="demo-history") as writer:
        pending = None
        for reached, events in simulate(
            ros_map, robots, start_ms + 1000, now_ms, seed=seed, prefix=prefix, thresholds=th
        ):
            if pending is not None:
                pending.result()
            pending = writer.submit(write, events)
            if progress is not None:
                done = min(1.0, (reached - start_ms) / (now_ms - start_ms))
                progress(SIMULATION_SHARE * done)
        if pending is not None:
            pending.result()
    poses, chunk_writes, conflicts = totals["poses"], totals["chunk_writes"], totals["conflicts"]
    snapshots = (
        store.build_snapshots_bulk(now_ms)
        if hasattr(store, "build_snapshots_bulk")
        else store.build_snapshots(now_ms)
    )
    found = store_incidents(
        store,
        start_ms,
        now_ms,
        th,
        None
        if progress is None
        else lambda done: progress(SIMULATION_SHARE + (1 - SIMULATION_SHARE) * done),
    )
    result = BackfillResult(
        start_ms,
        now_ms,
        poses,
        chunk_writes,
        conflicts,
        snapshots,
        sum(found.values()),
        round(time.monotonic() - started, 1),
    )
    log.info("demo history written", **dict(vars(result).items()))
    return result
