"""The endurance test's check of what the processors found over the retention: the
incidents the API lists and its heatmaps, against the rules (`detect_all`, the heatmap
rule's fold) over everything the drive had acknowledged."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from mapservice.core.annotations import ZoneViolation
from mapservice.core.event_incidents import EventRecords, detect_all, grows_with_the_clock
from mapservice.core.heatmaps import (
    BUCKET_MS,
    FINEST_CELL_M,
    Heatmap,
    HeatmapRule,
    fold_heatmap,
    incident_cells,
)
from mapservice.core.incident_model import meets
from mapservice.core.incidents import IncidentThresholds
from mapservice.core.ports import ConflictRow

from .endurance_kit import Drive, incident_fields

DAY_MS = 86_400_000
# An ongoing silence's end is the API's clock when it answers, the rules' the checks' clock.
ONGOING_END_TOLERANCE_MS = 120_000


def check_findings(
    get: Callable[..., Any],
    drive: Drive,
    now_ms: Callable[[], int],
    th: IncidentThresholds,
    lo: int,
    now: int,
    zone_robot: str,
    retention_days: int,
) -> None:
    """The incidents listed over [lo, now) and the heatmaps of its whole buckets (`get`:
    the API's JSON for a path and its parameters) equal what the rules find over the
    drive's acknowledged poses and records; `zone_robot` drives through the keep-out zone."""
    # The incidents of the retention: what the rules find in everything acknowledged (read
    # from a day before it, longer than any incident here but the last silences), as found
    # live through every restart. Every field is compared exactly but an ongoing silence's
    # end and length, which are the clock's of whoever answers (within a tolerance).
    since = lo - DAY_MS
    poses = [p for p in drive.pose_rows if p.ts_ms >= since]
    records = EventRecords(
        violations=[
            ZoneViolation(p.ts_ms, p.robot_id, "zone-wash", p.x, p.y)
            for p in poses
            if p.robot_id == zone_robot
        ],
        conflicts=[ConflictRow(*c) for c in drive.conflicts if c[2] >= since],
    )
    listed = get("/api/v1/incidents", **{"from": str(lo), "to": str(now), "limit": "100000"})
    assert not listed["truncated"]
    recomputed = detect_all(poses, records, now_ms(), th)
    want_incidents = [i for i in recomputed if meets(i, lo, now)]
    got_incidents = {i["id"]: i for i in listed["incidents"]}
    assert {k: incident_fields(i) for k, i in got_incidents.items()} == {
        i.incident_id: incident_fields(i) for i in want_incidents
    }
    answered = now_ms()
    for i in want_incidents:
        if grows_with_the_clock(i):
            assert i.end_ms - ONGOING_END_TOLERANCE_MS <= got_incidents[i.incident_id]["end_ms"]
            assert got_incidents[i.incident_id]["end_ms"] <= answered
    kinds = {i.kind for i in want_incidents}
    assert {"stuck", "near_miss", "battery_low", "offline", "zone_violation", "conflict"} <= kinds
    for kind in ("stuck", "near_miss", "battery_low"):  # the scenes': ~3 a day
        assert sum(i.kind == kind for i in want_incidents) >= retention_days * 2, kind

    # The heatmaps of the retention's whole buckets: the rule's fold of the acknowledged
    # poses (occupancy and dwell in samples, exactly; incidents where they were).
    h_from, h_to = -(-lo // BUCKET_MS) * BUCKET_MS, now // BUCKET_MS * BUCKET_MS
    want_map = Heatmap(
        h_from,
        h_to,
        FINEST_CELL_M,
        fold_heatmap(poses, h_from, h_to, 1, HeatmapRule.of(th)),
        incident_cells((i for i in recomputed if meets(i, h_from, h_to)), 1),
    )
    for kind in ("occupancy", "dwell", "incidents"):
        grid = get(
            "/api/v1/heatmap", **{"from": str(h_from), "to": str(h_to), "kind": kind, "cell": "0.5"}
        )
        assert {(i, j): v for i, j, v in grid["cells"]} == want_map.values(kind), kind
    occupancy = sum(want_map.values("occupancy").values())
    # a robot-second per pose: no robot reports twice in a second here
    assert occupancy == sum(h_from <= ts < h_to for _, ts in drive.poses)
    assert sum(want_map.values("dwell").values()) >= retention_days * 2  # the scenes stand
