"""Heatmaps of the floor over a span: where robots were (occupancy), where they stood still
(dwell), how fast they went (mean speed) and where incidents happened, per square cell; as
pure functions, the rule every store follows (the memory store folds with it; ClickHouse
pre-aggregates by it, and tests check one against the other).

**Samples.** A robot reports about once a second; it is counted once per whole UTC second
in which it reported: its first pose of that second (of its poses one per instant, as the
store keeps them) is a *sample*, worth one robot-second. A robot reporting faster counts
each second once, one reporting slower only the seconds it reported, and a robot silent
for a while counts nothing meanwhile (it is offline, not somewhere).

- **occupancy** of a cell: its samples, in robot-seconds.
- **speed** at a sample: the straight-line distance from the robot's previous sample over
  the time between them, if that time is at most the offline threshold (the robot was
  reporting throughout); unknown after a longer silence or at the robot's first sample.
  Positions are whole millimetres (as stored), so the rule is exact to the millimetre.
- **dwell** of a cell: its samples with a known speed below the incidents' moving
  threshold (the robot stood, or crept), in seconds.
- **mean speed** of a cell: the mean of its samples' known speeds, m/s (None without one).
- **incidents** of a cell: the incidents (as found, meeting the span) whose place lies in it.

A sample belongs to the span [from, to) if its second starts there; its previous sample may
lie before the span (the rule looks back one offline threshold). Cells are squares of
`FINEST_CELL_M` times a whole factor, cell (i, j) covering [i*size, (i+1)*size) in x and
[j*size, (j+1)*size) in y, map coordinates: a coarser cell holds exactly its finer ones.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Literal, NamedTuple, TypeVar

import msgspec

from mapservice.core.incident_model import Incident, IncidentThresholds, Placed

FINEST_CELL_MM = 500
FINEST_CELL_M = FINEST_CELL_MM / 1000
MAX_CELL_FACTOR = 40  # cells up to 20 m
DEFAULT_CELL_M = 0.5
SAMPLE_MS = 1000
# The pre-aggregation's time buckets (ClickHouse: heatmap_cells): a span is whole buckets
# plus at most one partial bucket at each end, read from the poses.
BUCKET_MS = 600_000

Kind = Literal["occupancy", "dwell", "speed", "incidents"]
KINDS: tuple[Kind, ...] = ("occupancy", "dwell", "speed", "incidents")
UNITS: dict[str, str] = {
    "occupancy": "robot-seconds",
    "dwell": "seconds",
    "speed": "m/s",
    "incidents": "incidents",
}


P = TypeVar("P", bound=Placed)


@dataclass(frozen=True)
class HeatmapRule:
    """The thresholds the rule uses: the incidents' moving speed and offline silence."""

    moving_m_s: float = IncidentThresholds.moving_m_s
    offline_after_ms: int = IncidentThresholds.offline_after_ms

    @classmethod
    def of(cls, thresholds: IncidentThresholds) -> HeatmapRule:
        return cls(thresholds.moving_m_s, thresholds.offline_after_ms)

    @property
    def lookback_ms(self) -> int:
        """How far before a span its first samples' previous samples may lie, rounded up
        to whole seconds (so the first second read is read whole)."""
        return -(-self.offline_after_ms // SAMPLE_MS) * SAMPLE_MS


class HeatmapCell(msgspec.Struct, frozen=True, gc=False, array_like=True):
    """One cell's sums over the span: samples (robot-seconds), still samples (dwell
    seconds), samples with a known speed and the sum of those speeds (m/s)."""

    i: int
    j: int
    samples: int
    still: int
    speeds: int
    speed_sum: float


def cell_factor(cell_m: float) -> int:
    """The whole number of finest cells a side of a `cell_m` cell is; ValueError (with the
    sizes allowed) for any other size."""
    within = math.isfinite(cell_m) and 0 < cell_m < 2 * MAX_CELL_FACTOR * FINEST_CELL_M
    factor = round(cell_m / FINEST_CELL_M) if within else 0
    if not 1 <= factor <= MAX_CELL_FACTOR or abs(factor * FINEST_CELL_M - cell_m) > 1e-9:
        raise ValueError(
            f"cell ({cell_m} m) must be a multiple of {FINEST_CELL_M} m from {FINEST_CELL_M} "
            f"to {MAX_CELL_FACTOR * FINEST_CELL_M:g} m (the heatmaps are kept per "
            f"{FINEST_CELL_M} m cell)"
        )
    return factor


def _mm(metres: float) -> int:
    return round(metres * 1000)


def samples_of(track: Sequence[P]) -> list[P]:
    """One robot's samples: its first pose of each whole second (`track` in time order)."""
    out: list[P] = []
    for pose in track:
        if not out or pose.ts_ms // SAMPLE_MS != out[-1].ts_ms // SAMPLE_MS:
            out.append(pose)
    return out


def fold_heatmap(
    poses: Iterable[Placed], from_ms: int, to_ms: int, factor: int, rule: HeatmapRule
) -> list[HeatmapCell]:
    """The cells of `factor` finest cells a side holding a sample of [from_ms, to_ms), by
    (i, j); `poses` in any order, one per robot and instant (the module's rule)."""
    start = from_ms // SAMPLE_MS * SAMPLE_MS - rule.lookback_ms
    tracks: dict[str, list[Placed]] = defaultdict(list)
    for pose in poses:
        if start <= pose.ts_ms < to_ms:
            tracks[pose.robot_id].append(pose)
    side = FINEST_CELL_MM * factor
    sums: dict[tuple[int, int], list[float]] = {}
    for track in tracks.values():
        track.sort(key=lambda p: p.ts_ms)
        previous: Placed | None = None
        for sample in samples_of(track):
            before, previous = previous, sample
            if sample.ts_ms // SAMPLE_MS * SAMPLE_MS < from_ms:
                continue
            x, y = _mm(sample.x), _mm(sample.y)
            cell = sums.setdefault((x // side, y // side), [0, 0, 0, 0.0])
            cell[0] += 1
            if before is None or sample.ts_ms - before.ts_ms > rule.offline_after_ms:
                continue
            dx, dy, dt = x - _mm(before.x), y - _mm(before.y), sample.ts_ms - before.ts_ms
            reach = rule.moving_m_s * dt  # millimetres in dt at the moving speed
            cell[1] += dx * dx + dy * dy < reach * reach
            cell[2] += 1
            cell[3] += (dx * dx + dy * dy) ** 0.5 / dt  # mm/ms is m/s
    return [
        HeatmapCell(i, j, int(n), int(still), int(speeds), total)
        for (i, j), (n, still, speeds, total) in sorted(sums.items())
    ]


def incident_cells(incidents: Iterable[Incident], factor: int) -> dict[tuple[int, int], int]:
    """How many of `incidents` lie in each cell of `factor` finest cells a side."""
    side = FINEST_CELL_MM * factor
    counts: dict[tuple[int, int], int] = defaultdict(int)
    for incident in incidents:
        counts[(_mm(incident.x) // side, _mm(incident.y) // side)] += 1
    return dict(counts)


class CountedIncidents(NamedTuple):
    """The incidents per cell of a span (`incident_cells` of the first `limit` of them as
    the incidents list orders them) and whether more than `limit` met the span."""

    cells: dict[tuple[int, int], int]
    truncated: bool


def count_incidents(listed: Sequence[Incident], factor: int, limit: int) -> CountedIncidents:
    """`listed`: a span's incidents in the list's order, `limit` + 1 of them when more meet it."""
    return CountedIncidents(incident_cells(listed[:limit], factor), len(listed) > limit)


@dataclass(frozen=True)
class Heatmap:
    """A span's cells at one size, every measure: `cells` those with a sample, `incidents`
    the counts of those with an incident (either may hold a cell the other lacks)."""

    from_ms: int
    to_ms: int
    cell_m: float
    cells: Sequence[HeatmapCell]
    incidents: dict[tuple[int, int], int]

    def values(self, kind: Kind) -> dict[tuple[int, int], float]:
        """The cells' values of one kind, those that have one."""
        if kind == "incidents":
            return {k: float(v) for k, v in self.incidents.items()}
        if kind == "occupancy":
            return {(c.i, c.j): float(c.samples) for c in self.cells}
        if kind == "dwell":
            return {(c.i, c.j): float(c.still) for c in self.cells if c.still}
        return {(c.i, c.j): c.speed_sum / c.speeds for c in self.cells if c.speeds}

    def rows(self) -> list[tuple[int, int, int, int, float | None, int]]:
        """Per cell with anything, by (i, j): occupancy s, dwell s, mean speed, incidents."""
        by_cell = {(c.i, c.j): c for c in self.cells}
        out = []
        for key in sorted(by_cell.keys() | self.incidents.keys()):
            c = by_cell.get(key)
            out.append(
                (
                    *key,
                    c.samples if c else 0,
                    c.still if c else 0,
                    c.speed_sum / c.speeds if c and c.speeds else None,
                    self.incidents.get(key, 0),
                )
            )
        return out
