"""Endurance on a simulated clock through the real pipeline as `mapservice up` runs it
(Mosquitto, gateway, Kafka, `mapservice clickhouse-server` owning the chDB directory,
processors with their snapshot, repair and retention timers, the API apart): 25 simulated
days with the default retention of seven (three retention periods and more) in about five
real minutes.

Robots publish poses over MQTT at QoS 1, the floor is published once at the start and a
pallet moves every six simulated hours, every second time rewritten 20 s later by another
robot (a conflict). An operator annotates the floor through the API (a keep-out zone the
first robot drives through, points of interest; one moved, one removed, the zone renamed
late): the annotations are state and stand through every retention, the zone's violations
are history and go with it. Every few simulated hours the other two robots play a scene
for the incident rules (Drive.scene: one stuck with a path ahead, the other passing close
by with its battery running low), and every robot falls silent between its poses (offline). Each component is restarted along the way: the processors,
the API, the ClickHouse server, the gateway, the MQTT broker and, where the stack's Kafka
keeps its records across a restart, the Kafka broker (tansu keeps them in memory: that
step is skipped with a warning that says so). Once a simulated day the bytes of the history's active parts are
read through the API's /clickhouse (analyst SQL on system.tables): after the first
retention period they stay flat.

At the end the processors and API are restarted once more with their clock slowed to real
time (so the checks do not race the retention), and many instants of the retention are
read through the API and checked against a brute-force fold of everything acknowledged:
the map at T, the 2019 `latest=true&updatedBefore=T` listing with its pixels, the robots
at T and the annotations at T; the timeline, the conflicts, the change feed and the zone
violations of the whole retention; the incidents of the retention against the rules'
recomputation (`detect_all`) over everything acknowledged, and its occupancy, dwell and
incident heatmaps against the heatmap rule's fold of the poses; then, with the stack
stopped, no snapshot names missing pixels, the heatmap buckets hold the samples of their
ten minutes, and the days before the retention are gone (chunk writes, zone violations,
incidents, heatmap buckets, the removed annotation's edits) while the standing
annotations' are kept.
"""

from __future__ import annotations

import base64
import time
import warnings
import zlib

import httpx
import pytest

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.adapters.ros_map import load_ros_map, meta_for, slice_chunks
from mapservice.core.heatmaps import BUCKET_MS, SAMPLE_MS
from mapservice.core.timetravel import fold_map
from mapservice.core.wire2019 import format_timestamp
from mapservice.local.stack import Stack
from mapservice.processors.incident_watch import thresholds_of
from mapservice.settings import Settings
from tests.fixtures.paths import MAPS

from .conftest import wait_for_meta
from .endurance_findings import check_findings
from .endurance_kit import (
    Drive,
    Operator,
    SimClock,
    bytes_by_table,
    kafka_keeps_records,
    oldest_history_ms,
)

# Its simulated clock runs against real time (a restart costs simulated hours) and the
# storage per simulated day is judged: beside another test's stack the bounds are missed.
pytestmark = pytest.mark.alone

DAY = 86_400_000
HOUR = 3_600_000
RETENTION_DAYS = Settings.model_fields["retention_days"].default  # the default: 7
SIM_DAYS = 25
ROBOTS = ("end-1", "end-2", "end-3")
POSES_PER_TURN = 6  # per robot and turn of the drive loop (~0.2 real s, ~30 simulated min)
CONFLICT_GAP_MS = 20_000  # within the 60 s conflict window
SCENE_EVERY_MS = 8 * HOUR  # the incident scenes (Drive.scene), away from the chunk changes
SCENE_AFTER_MS = 60_000  # a scene begins this long after the turn's previous poses
# Restarts along the way (simulated day: component). "kafka" only where its broker keeps
# its records across a restart (kafka_keeps_records).
RESTARTS = {
    4.3: "processors",
    6.8: "api",
    9.4: "gateway",
    11.6: "clickhouse",
    14.2: "mqtt",
    19.3: "kafka",
}
# The operator's annotations (simulated day: edit), away from the API's restart. The first
# robot drives at x 1.0-1.5 m, y 2 m (the others further right): inside the zone.
KEEP_OUT = {
    "shape": "zone",
    "name": "wash bay",
    "kind": "keep_out",
    "polygon": [[0.8, 1.7], [1.7, 1.7], [1.7, 2.3], [0.8, 2.3]],
}
DOCK = {"shape": "poi", "name": "dock", "kind": "station", "x": 5.0, "y": 3.0, "heading": 0.0}
NOTE = {"shape": "poi", "name": "spill", "kind": "note", "x": 7.0, "y": 4.0}
EDITS = {
    1.0: ("create", "zone-wash", KEEP_OUT),
    1.1: ("create", "poi-dock", DOCK),
    2.0: ("create", "poi-spill", NOTE),
    3.5: ("change", "poi-dock", {**DOCK, "x": 6.0}),
    5.5: ("remove", "poi-spill", None),
    21.0: ("change", "zone-wash", {**KEEP_OUT, "name": "wash bay 2"}),
}
# Storage per simulated day. After the first retention period (days RETENTION_DAYS + 2 on)
# within FLAT_BOUND of its smallest day; once the floor was also renewed the first time (a
# copy of its contents a week, dropped with the week: days 2 * RETENTION_DAYS + 1 on) within
# STEADY_BOUND. Measured in two runs with the incidents (a third of the bytes: ~1,200 a
# simulated day, most of them silences between the drive's sparse poses, each rewritten
# as it is found again): 714-1,034 kB and 750-1,115 kB on days 9-24, 827-1,034 kB and
# 844-1,115 kB on days 15-24 (parts not yet merged make a day's figure vary by ~15 %, the
# incidents' replaced rows more); a history that kept everything (the retention stopped
# after the ClickHouse restart, as it once did) grew 2.4x from day 14 to 24, 2.1x from 15.
FLAT_BOUND = 1.7
STEADY_BOUND = 1.45


@pytest.fixture(scope="module")
def sim_stack(tmp_path_factory):
    real_now = time.time_ns() // 1_000_000
    # The stack takes a while to start: the clock starts then, far in the past, where no
    # real clock can expire anything.
    clock = SimClock(real_now - 40 * DAY, real_now + 20_000)
    env = {
        **clock.env(),
        "MAPSERVICE_SNAPSHOT_EVERY_S": "10800",
        "MAPSERVICE_SNAPSHOT_GRACE_S": "600",
        "MAPSERVICE_MAX_FUTURE_SKEW_S": "7200",
    }
    stack = Stack(tmp_path_factory.mktemp("endurance"), mqtt="mosquitto", extra_env=env, apart=True)
    stack.start(
        stack.start_brokers,
        lambda: stack.publish_meta(meta_for(load_ros_map(MAPS / "depot.yaml"))),
        stack.start_apart,
        stack.start_gateway,
        lambda: wait_for_meta(stack),
    )
    yield stack, clock
    stack.stop()


@pytest.mark.timeout(600)  # the bound: at most ten minutes
def test_25_days_with_every_restart_through_the_pipeline(sim_stack) -> None:
    stack, clock = sim_stack
    while clock.now_ms() < clock.start_ms:
        time.sleep(0.1)
    depot = load_ros_map(MAPS / "depot.yaml")
    floor = slice_chunks(depot)
    meta = meta_for(depot)
    drive = Drive(stack)
    operator = Operator(stack)
    edits_due = dict(EDITS)
    th = thresholds_of(stack.settings())
    started = time.monotonic()
    t0 = clock.now_ms()
    for (row, column), pixels in sorted(floor.items()):
        drive.chunk(row, column, t0, "mapper", pixels)
    end = t0 + SIM_DAYS * DAY
    next_change, changes, last_ts = t0 + 6 * HOUR, 0, t0
    next_scene, scenes = t0 + 3 * HOUR, 0
    pallet = (meta.chunk_rows // 2, meta.chunk_cols // 2)
    size = meta.chunk_width * meta.chunk_height
    restarts_due = dict(RESTARTS)
    restart_seconds: dict[str, float] = {}  # real seconds each restart held the drive
    bytes_per_day: dict[int, int] = {}
    tables_per_day: dict[int, dict[str, int]] = {}
    skipped: list[str] = []
    try:
        while (now := clock.now_ms()) < end:
            in_scene: tuple[str, ...] = ()
            if now >= next_scene:
                scenes += 1
                in_scene = (ROBOTS[1], ROBOTS[2])[:: 1 if scenes % 2 else -1]
                assert drive.scene(*in_scene, last_ts + SCENE_AFTER_MS, th) < now
                next_scene += SCENE_EVERY_MS
            for k in range(POSES_PER_TURN):  # spread over the simulated time since the last turn
                ts = last_ts + (now - last_ts) * (k + 1) // POSES_PER_TURN
                for i, robot in enumerate(ROBOTS):
                    if robot not in in_scene:
                        drive.pose(robot, ts - i, 1.0 + i + k / 10)
            last_ts = now
            if now >= next_change:
                changes += 1
                a = drive.chunk(
                    *pallet, now, ROBOTS[changes % 3], bytes([changes % 200 + 20]) * size
                )
                if changes % 2 == 0:  # another robot sees it otherwise: a conflict
                    b = drive.chunk(
                        *pallet,
                        now + CONFLICT_GAP_MS,
                        ROBOTS[(changes + 1) % 3],
                        bytes([changes % 200 + 21]) * size,
                    )
                    drive.conflicts.add((a.row, a.column, b.ts_ms, a.robot_id, a.ts_ms, b.robot_id))
                next_change += 6 * HOUR
            drive.acknowledged()
            day = (now - t0) / DAY
            if int(day) not in bytes_per_day and (tables := bytes_by_table(stack)):
                bytes_per_day[int(day)] = sum(tables.values())
                tables_per_day[int(day)] = tables
            for at, (change, annotation_id, body) in list(edits_due.items()):
                if day >= at:
                    del edits_due[at]
                    operator.edit(change, annotation_id, body, clock)
            for at, component in list(restarts_due.items()):
                if day < at:
                    continue
                del restarts_due[at]
                if component == "kafka" and not kafka_keeps_records(stack):
                    skipped.append(
                        "the Kafka broker's restart: tansu keeps its records in memory "
                        "and loses them on a restart"
                    )
                    warnings.warn(f"endurance: skipped {skipped[-1]}", stacklevel=2)
                    continue
                restarted = time.monotonic()
                stack.restart(component)
                if component == "mqtt":  # the robots' client reconnects, then publishes again
                    drive.wait_connected()
                restart_seconds[component] = round(time.monotonic() - restarted, 1)
            time.sleep(0.2)
    finally:
        drive.close()
    drive_s = time.monotonic() - started
    print(
        f"\nendurance: {SIM_DAYS} simulated days driven in {drive_s:.0f} s; skipped: {skipped or 'nothing'}"
    )
    print("endurance: history bytes per simulated day:", bytes_per_day)
    print("endurance: real seconds per restart:", restart_seconds)
    for d in (RETENTION_DAYS + 2, 2 * RETENTION_DAYS + 1, max(tables_per_day)):
        print(f"endurance: history bytes by table on day {d}:", tables_per_day.get(d))
    checks_started = time.monotonic()

    # A conflict's incident is found with the batch or tick after the conflict is stored; one
    # not yet judged when the processors stop is not judged after a restart later than
    # their memory's span (MAPSERVICE_INCIDENT_MEMORY_S of the clock: at the drive's clock
    # every restart is). The restart below is the test's, not the floor's: the drive's last
    # conflicts are given the time to be judged first.
    recent = clock.now_ms() - (RETENTION_DAYS - 1) * DAY
    want_judged = {c[2] for c in drive.conflicts if c[2] >= recent}
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        r = httpx.get(
            f"{stack.api_url}/api/v1/incidents",
            params={"from": str(recent), "to": str(clock.now_ms()), "kind": "conflict"},
            timeout=30,
        )
        if r.status_code == 200 and want_judged <= {i["start_ms"] for i in r.json()["incidents"]}:
            break
        time.sleep(0.5)

    # The processors and API again, their clock slowed to real time where it stands: the
    # checks below read a retention that does not move under them. The snapshot timer ticks
    # every second (at real time its period would be 30 s): under load it may still be
    # catching up the snapshots and retention steps the drive's restarts cost, and the
    # checks of what the retention dropped need its step at this clock.
    clock = SimClock(clock.now_ms(), time.time_ns() // 1_000_000, rate=1)
    stack.extra_env.update({**clock.env(), "MAPSERVICE_SNAPSHOT_TICK_S": "1"})
    stack.restart("processors")
    stack.restart("api")
    api = httpx.Client(base_url=stack.api_url, timeout=30)

    def get(path: str, **params):
        r = api.get(path, params=params)
        assert r.status_code == 200, r.text
        return r.json()

    # Everything acknowledged reaches the history (the gateway had a backlog after its restart).
    last_pose = {r: max(ts for rr, ts in drive.poses if rr == r) for r in ROBOTS}
    deadline = time.monotonic() + 120
    while True:
        seen = {r["robotId"]: r["ts_ms"] for r in get("/api/v1/robots")["robots"]}
        if all(seen.get(r) == last_pose[r] for r in ROBOTS) or time.monotonic() > deadline:
            break
        time.sleep(1)
    assert {r: seen.get(r) for r in ROBOTS} == last_pose
    time.sleep(3)  # the views (timeline, conflicts) follow the history within a second or so

    now = clock.now_ms()
    lo = now - RETENTION_DAYS * DAY + 60_000
    pixels = {(w.row, w.column, w.content_hash): w.pixels for w in drive.written}
    instants = (
        [lo, lo + HOUR]
        + [
            lo + int(f * (now - lo))
            for f in (0.05, 0.12, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95)
        ]
        + [end - HOUR, now]
    )
    for t in instants:
        want = fold_map(drive.written, t)
        got = get("/api/v1/map", at=str(t))["chunks"]
        assert {(c["row"], c["column"]): c["content_hash"] for c in got} == {
            k: v.content_hash for k, v in want.items()
        }, f"map at {format_timestamp(t)}"
        listing = get(
            "/api/chunk-service/chunks", latest="true", updatedBefore=str(t + 1), limit="10000"
        )
        assert len(listing) == len(want) == len(floor), f"2019 listing at {format_timestamp(t)}"
        for doc in listing:
            w = want[(doc["row"], doc["column"])]
            assert doc["chunk"] is not None, "the 2019 listing names pixels that are gone"
            assert (
                zlib.decompress(base64.b64decode(doc["chunk"]))
                == pixels[(w.row, w.column, w.content_hash)]
            )
        robots = {r["robotId"]: r["ts_ms"] for r in get("/api/v1/robots", at=str(t))["robots"]}
        want_robots = {r: max(ts for rr, ts in drive.poses if rr == r and ts <= t) for r in ROBOTS}
        assert {r: robots.get(r) for r in ROBOTS} == want_robots, f"robots at {format_timestamp(t)}"
        annotations = {
            a["id"]: (a["annotation"], a["created_ms"], a["changed_ms"])
            for a in get("/api/v1/annotations", at=str(t))["annotations"]
        }
        assert annotations == operator.standing_at(t), f"annotations at {format_timestamp(t)}"
    # Created a retention and more ago: the zone and the dock stand, the dock moved.
    assert set(operator.standing_at(lo)) == {"zone-wash", "poi-dock"}
    assert not edits_due, f"edits not made: {edits_due}"

    # The timeline and the conflicts of the whole retention, against the brute force.
    buckets = RETENTION_DAYS * 4
    timeline = get("/api/v1/timeline", **{"from": str(lo), "to": str(now), "buckets": str(buckets)})
    assert (timeline["from_ms"], timeline["to_ms"]) == (lo, now)
    span, got_buckets = timeline["bucket_ms"], timeline["buckets"]
    want_changes, want_conflicts = [0] * len(got_buckets), [0] * len(got_buckets)
    want_active: list[set] = [set() for _ in got_buckets]
    for w in drive.written:
        if lo <= w.ts_ms < now:
            want_changes[(w.ts_ms - lo) // span] += 1
    for c in drive.conflicts:
        if lo <= c[2] < now:
            want_conflicts[(c[2] - lo) // span] += 1
    for robot, ts in drive.poses:
        if lo <= ts < now:
            want_active[(ts - lo) // span].add(robot)
    assert [b["chunk_changes"] for b in got_buckets] == want_changes
    assert [b["conflicts"] for b in got_buckets] == want_conflicts
    assert [b["robots_active"] for b in got_buckets] == [len(s) for s in want_active]
    conflicts = get("/api/v1/conflicts", **{"from": str(lo), "to": str(now)})
    assert {
        (c["row"], c["column"], c["ts_ms"], c["robot_a"], c["ts_a_ms"], c["robot_b"])
        for c in conflicts["conflicts"]
    } == {c for c in drive.conflicts if lo <= c[2] < now}
    assert sum(want_conflicts) >= RETENTION_DAYS  # two a day: the check means something

    # The change feed and the zone's violations: the history of the retention, exactly.
    changes = get("/api/v1/changes", **{"from": str(lo), "to": str(now), "limit": "1000"})
    assert changes["next"] is None
    # A write that leaves its chunk's content as it was is no change (a move's first write
    # often restores what the last conflict's second write put there).
    want_feed, content = set(), {}
    for w in sorted(drive.written, key=lambda w: (w.ts_ms, w.robot_id)):
        before = content.get((w.row, w.column))
        if lo <= w.ts_ms < now and before != w.content_hash:
            want_feed.add((w.ts_ms, w.row, w.column, w.robot_id, w.content_hash, before))
        content[(w.row, w.column)] = w.content_hash
    assert {
        (c["ts_ms"], c["row"], c["column"], c["robot_id"], c["content_hash"], c["previous_hash"])
        for c in changes["changes"]
    } == want_feed
    assert len(want_feed) >= RETENTION_DAYS * 2  # a few a day: the check means something
    assert all(c["kind"] == "change" for c in changes["changes"])
    violations = get(
        "/api/v1/zone-violations", **{"from": str(lo), "to": str(now), "limit": "100000"}
    )
    assert not violations["truncated"]
    want_violations = {
        (ROBOTS[0], ts) for robot, ts in drive.poses if robot == ROBOTS[0] and lo <= ts < now
    }
    assert {(v["robotId"], v["ts_ms"]) for v in violations["violations"]} == want_violations
    assert {v["zoneId"] for v in violations["violations"]} == {"zone-wash"}

    # The incidents and heatmaps of the retention against the rules over what was acknowledged.
    check_findings(get, drive, clock.now_ms, th, lo, now, ROBOTS[0], RETENTION_DAYS)
    # The retention's step at this clock (its timer may have been days behind): checked
    # below, with the stack stopped.
    kept_from = end - (RETENTION_DAYS + 1) * DAY
    deadline = time.monotonic() + 120
    while ((oldest := oldest_history_ms(stack)) is None or oldest < kept_from) and (
        time.monotonic() < deadline
    ):
        time.sleep(1)
    api.close()
    stack.stop()
    print(f"endurance: checks through the API in {time.monotonic() - checks_started:.0f} s")

    store = ClickHouseStore.from_settings(stack.settings())
    try:
        db = store.database
        missing = store.rows(
            f"SELECT count() FROM {db}.map_snapshots WHERE content_hash NOT IN "
            f"(SELECT content_hash FROM {db}.chunk_contents)",
            {},
        )[0][0]
        assert missing == 0, "a snapshot names pixels that are gone"
        ((oldest,),) = store.rows(
            f"SELECT toUnixTimestamp64Milli(min(ts)) FROM {db}.chunk_events", {}
        )
        assert oldest >= kept_from, "days before the retention were kept"
        ((oldest_violation, violations_kept),) = store.rows(
            f"SELECT toUnixTimestamp64Milli(min(ts)), count() FROM {db}.zone_violations", {}
        )
        assert violations_kept and oldest_violation >= kept_from, (
            "zone violations before the retention were kept"
        )
        ((oldest_incident, incidents_kept),) = store.rows(
            f"SELECT toUnixTimestamp64Milli(min(start)), count() FROM {db}.incidents", {}
        )
        assert incidents_kept and oldest_incident >= kept_from, (
            "incidents before the retention were kept"
        )
        # Each bucket kept holds its ten minutes' samples (one a robot and second) and
        # none before the retention is kept; none between the first and last is missing.
        kept_buckets = dict(
            store.rows(
                f"SELECT toUnixTimestamp(bucket) * 1000 AS b, sum(samples) "
                f"FROM {db}.heatmap_cells FINAL GROUP BY b ORDER BY b",
                {},
            )
        )
        assert kept_buckets and min(kept_buckets) >= kept_from, (
            "heatmap buckets before the retention were kept"
        )
        assert max(kept_buckets) >= end - DAY, "the heatmap buckets stopped being built"
        samples: dict[int, int] = {}
        for _robot, second in {(r, ts // SAMPLE_MS) for r, ts in drive.poses}:
            bucket = second * SAMPLE_MS // BUCKET_MS * BUCKET_MS
            if min(kept_buckets) <= bucket <= max(kept_buckets):
                samples[bucket] = samples.get(bucket, 0) + 1
        assert kept_buckets == samples
        kept_edits = store.rows(
            f"SELECT annotation_id, change FROM {db}.annotation_events FINAL ORDER BY ts", {}
        )
        # The standing annotations keep their creation and latest edit however old; the
        # removed one's edits went with the retention.
        assert kept_edits == [
            ("zone-wash", "created"),
            ("poi-dock", "created"),
            ("poi-dock", "changed"),
            ("zone-wash", "changed"),
        ], kept_edits
    finally:
        store.close()

    # Storage per simulated day: flat after the first retention period.
    after_first = {d: b for d, b in bytes_per_day.items() if d >= RETENTION_DAYS + 2}
    steady = {d: b for d, b in after_first.items() if d >= 2 * RETENTION_DAYS + 1}
    assert len(after_first) >= SIM_DAYS - RETENTION_DAYS - 4, (
        f"too few days measured: {bytes_per_day}"
    )
    assert len(steady) >= SIM_DAYS - 2 * RETENTION_DAYS - 3, (
        f"too few days measured: {bytes_per_day}"
    )
    assert max(after_first.values()) <= FLAT_BOUND * min(after_first.values()), (
        f"storage grows after the first retention period: {bytes_per_day}"
    )
    assert max(steady.values()) <= STEADY_BOUND * min(steady.values()), (
        f"storage grows in the steady state: {bytes_per_day}"
    )
