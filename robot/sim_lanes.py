"""Keeping to one side: a robot drives its planned route a lateral offset to the right of the
route's centre line where the free space allows, as AMRs sharing a floor do. Two robots
meeting head-on in an aisle then pass an offset or two apart instead of both driving down its
middle, and the ones whose routes cross still give way (robot/sim_traffic.py).

The planner's route joins cell centres (robot/planning.py); here each centre is moved to the
right of the route's direction, as far as `offset_px` where the straight line out to it stays
on ok cells (the inflated free space: a robot's centre on an ok cell keeps its body off the
racks), less where the aisle is narrower, not at all in a doorway. The offset grows from
nothing after the start and shrinks to nothing before the goal (stations and chargers are
cells' centres) at a bounded slope, so the robot drifts across rather than jumping. Every
segment of the result is checked cell by cell against the grid, where it was thinned too, so
a kept-to-the-side route never leaves the ok cells the centre line ran on.
"""

from __future__ import annotations

import math

from .planning import Cell, PlanGrid, simplify

Point = tuple[float, float]  # continuous image coordinates (u = column, v = row)

# How far sideways a robot drifts per distance ahead when it moves into or out of its side.
DRIFT_SLOPE = 0.5
# The fractions of the offset tried where the whole of it does not fit, largest first.
OFFSET_STEPS = (1.0, 0.75, 0.5, 0.25)
# How far (in offsets) the route's direction is looked at around each cell: the sideways
# move follows the route's general direction, not each step of a diagonal's staircase.
DIRECTION_SPAN = 1.0
# How far a thinned route may stray from the moved centres (in cells).
THIN_TOLERANCE = 0.2


def keep_to_side(grid: PlanGrid, cells: list[Cell], offset_px: float) -> tuple[Point, ...]:
    """Waypoints along the planned `cells` (ok cells, adjacent, start and goal included),
    kept to the right of the centre line by up to `offset_px`; the centre line's simplified
    waypoints when the offset is 0 or the route too short to move aside."""
    if offset_px <= 0 or len(cells) < 3:
        return tuple(grid.centre_px(c) for c in simplify(cells))
    centres = [grid.centre_px(c) for c in cells]
    normals = _right_normals(centres, max(2, math.ceil(DIRECTION_SPAN * offset_px / grid.cell_px)))
    room = [_room(grid, p, n, offset_px) for p, n in zip(centres, normals, strict=True)]
    room[0] = room[-1] = 0.0
    while True:
        offsets = _ramped(room, centres)
        points = [
            (p[0] + n[0] * o, p[1] + n[1] * o)
            for p, n, o in zip(centres, normals, offsets, strict=True)
        ]
        kept = _forward(points, normals, offsets)
        blocked = [
            (i, j)
            for i, j in zip(kept, kept[1:], strict=False)
            if not segment_clear(grid, points[i], points[j])
        ]
        if not blocked:
            break
        # Back to the centre line around a step that would cut a corner: between
        # neighbouring centres it is clear.
        for i, j in blocked:
            room[i : j + 1] = [0.0] * (j + 1 - i)
    route = [points[k] for k in kept]
    return tuple(_thinned(grid, route, THIN_TOLERANCE * grid.cell_px))


def _right_normals(centres: list[Point], span: int) -> list[Point]:
    """At each centre, the unit vector to the right of the route's direction there (image
    rows grow downwards: driving towards +u, the right is +v)."""
    n = len(centres)
    out = []
    for i in range(n):
        (u0, v0), (u1, v1) = centres[max(0, i - span)], centres[min(n - 1, i + span)]
        du, dv = u1 - u0, v1 - v0
        length = math.hypot(du, dv) or 1.0
        out.append((-dv / length, du / length))
    return out


def _room(grid: PlanGrid, centre: Point, normal: Point, offset_px: float) -> float:
    """The largest of the tried offsets whose straight way out from `centre` stays clear."""
    for share in OFFSET_STEPS:
        o = offset_px * share
        if segment_clear(grid, centre, (centre[0] + normal[0] * o, centre[1] + normal[1] * o)):
            return o
    return 0.0


def _ramped(room: list[float], centres: list[Point]) -> list[float]:
    """Offsets within each centre's room that change by at most `DRIFT_SLOPE` per distance
    along the route. Only ever lowered from the room, so each stays on its checked way out."""
    offsets = list(room)
    for i in range(1, len(offsets)):
        step = math.dist(centres[i - 1], centres[i]) * DRIFT_SLOPE
        offsets[i] = min(offsets[i], offsets[i - 1] + step)
    for i in range(len(offsets) - 2, -1, -1):
        step = math.dist(centres[i + 1], centres[i]) * DRIFT_SLOPE
        offsets[i] = min(offsets[i], offsets[i + 1] + step)
    return offsets


def _forward(points: list[Point], normals: list[Point], offsets: list[float]) -> list[int]:
    """The indices of the points to drive through: not the moved ones behind the last one
    kept (on the inside of a bend moved centres can fall back behind each other, and the
    robot would back up to reach them). The direction ahead is the normal turned back left."""
    kept = [0]
    for i in range(1, len(points) - 1):
        (nu, nv), last, p = normals[i], points[kept[-1]], points[i]
        if offsets[i] == 0 or (p[0] - last[0]) * nv - (p[1] - last[1]) * nu > 1e-9:
            kept.append(i)
    kept.append(len(points) - 1)
    return kept


def _thinned(grid: PlanGrid, points: list[Point], tolerance: float) -> list[Point]:
    """The points a robot needs (Ramer-Douglas-Peucker): a run is one straight segment when
    none of its points lies further than `tolerance` from it and the segment is clear."""
    keep = {0, len(points) - 1}
    todo = [(0, len(points) - 1)]
    while todo:
        first, last = todo.pop()
        if last - first < 2:
            continue
        a, b = points[first], points[last]
        far, at = max((_off_line(points[k], a, b), k) for k in range(first + 1, last))
        if far > tolerance or not segment_clear(grid, a, b):
            keep.add(at)
            todo += [(first, at), (at, last)]
    return [points[k] for k in sorted(keep)]


def _off_line(p: Point, a: Point, b: Point) -> float:
    """How far `p` lies from the segment a-b."""
    du, dv = b[0] - a[0], b[1] - a[1]
    length2 = du * du + dv * dv
    t = (
        0.0
        if length2 == 0
        else max(0.0, min(1.0, ((p[0] - a[0]) * du + (p[1] - a[1]) * dv) / length2))
    )
    return math.dist(p, (a[0] + du * t, a[1] + dv * t))


def segment_clear(grid: PlanGrid, a: Point, b: Point) -> bool:
    """Whether every cell the straight segment a-b touches is ok."""
    return all(grid.is_ok(cell) for cell in segment_cells(grid.cell_px, a, b))


def segment_cells(cell_px: int, a: Point, b: Point) -> list[Cell]:
    """The cells (row, col) of `cell_px` pixels that the segment a-b passes over, in order
    (a grid walk: the next cell is across whichever cell edge the segment meets first; through
    a cell's corner, both cells beside it too)."""
    (u0, v0), (u1, v1) = a, b
    col, row = int(u0 // cell_px), int(v0 // cell_px)
    last_col, last_row = int(u1 // cell_px), int(v1 // cell_px)
    du, dv = u1 - u0, v1 - v0
    step_c, step_r = (1 if du > 0 else -1), (1 if dv > 0 else -1)
    inf = math.inf
    # the part of the segment (0..1) at which it crosses the next column or row edge, and
    # the part from one edge to the next
    next_c = ((col + (step_c > 0)) * cell_px - u0) / du if du else inf
    next_r = ((row + (step_r > 0)) * cell_px - v0) / dv if dv else inf
    each_c = cell_px / abs(du) if du else inf
    each_r = cell_px / abs(dv) if dv else inf
    cells = [(row, col)]
    for _ in range(abs(last_col - col) + abs(last_row - row)):
        if (row, col) == (last_row, last_col):
            break
        if math.isclose(next_c, next_r, rel_tol=0.0, abs_tol=1e-9):
            cells += [(row + step_r, col), (row, col + step_c)]
            row, col, next_c, next_r = row + step_r, col + step_c, next_c + each_c, next_r + each_r
        elif next_c < next_r:
            col, next_c = col + step_c, next_c + each_c
        else:
            row, next_r = row + step_r, next_r + each_r
        cells.append((row, col))
    if cells[-1] != (last_row, last_col):  # rounding on a long segment: its end counts too
        cells.append((last_row, last_col))
    return cells
