"""Path planning on an inflated, coarse occupancy grid (A* with heapq).

The map is cut into square cells of `cell_px` pixels. A cell is *clear* when every pixel
in it is drivable, and *ok* (a robot may plan through it) when no non-clear cell lies
within `inflate` cells of it: the inflation keeps a robot's body off the racks. A path
joins centres of ok cells; each step stays inside the two cells it joins (diagonal steps
only where both side cells are ok too), so a path of ok cells never touches a pixel
that is not drivable.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field

import numpy as np

Cell = tuple[int, int]  # (row, col) on the coarse grid


@dataclass(frozen=True)
class PlanGrid:
    cell_px: int
    ok: np.ndarray  # bool (rows, cols)
    _pf: dict = field(default_factory=dict, compare=False, repr=False)  # derived, built once

    @property
    def shape(self) -> tuple[int, int]:
        return self.ok.shape  # type: ignore[return-value]

    def centre_px(self, cell: Cell) -> tuple[float, float]:
        """Continuous image coordinates (u = column, v = row) of a cell's centre."""
        return ((cell[1] + 0.5) * self.cell_px, (cell[0] + 0.5) * self.cell_px)

    def cell_at(self, u: float, v: float) -> Cell:
        return (int(v // self.cell_px), int(u // self.cell_px))

    def ok_padded(self) -> tuple[list[bool], int]:
        """`ok` framed by a border of not-ok cells, as one flat Python list (row-major), and
        its row length; built once. List indexing is what the searches do most, and the
        frame lets them step to a neighbour by adding an offset, without bounds checks.
        Flat indices grow with (row, col) as on the bare grid, so ties break the same."""
        padded = self._pf.get("padded")
        if padded is None:
            framed = np.pad(self.ok, 1, constant_values=False)
            padded = self._pf["padded"] = (framed.ravel().tolist(), framed.shape[1])
        return padded

    def is_ok(self, cell: Cell) -> bool:
        r, c = cell
        return 0 <= r < self.ok.shape[0] and 0 <= c < self.ok.shape[1] and bool(self.ok[r, c])


def disc(radius: int) -> list[tuple[int, int]]:
    return [
        (dr, dc)
        for dr in range(-radius, radius + 1)
        for dc in range(-radius, radius + 1)
        if dr * dr + dc * dc <= radius * radius + radius
    ]


def dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """Boolean dilation by a disc of `radius` cells (the grid is small: shifts are cheap)."""
    if radius <= 0:
        return mask.copy()
    padded = np.pad(mask, radius, constant_values=False)
    out = np.zeros_like(mask)
    h, w = mask.shape
    for dr, dc in disc(radius):
        out |= padded[radius + dr : radius + dr + h, radius + dc : radius + dc + w]
    return out


def build_grid(drivable: np.ndarray, cell_px: int, inflate: int) -> PlanGrid:
    """Coarse grid of `drivable` (bool, image rows x columns); pixels past the edge are not
    drivable."""
    h, w = drivable.shape
    rows, cols = -(-h // cell_px), -(-w // cell_px)
    padded = np.zeros((rows * cell_px, cols * cell_px), dtype=bool)
    padded[:h, :w] = drivable
    clear = padded.reshape(rows, cell_px, cols, cell_px).all(axis=(1, 3))
    return PlanGrid(cell_px, ~dilate(~clear, inflate))


def grid_for(
    drivable: np.ndarray, resolution: float, cell_m: float = 0.25, robot_radius_m: float = 0.3
) -> PlanGrid:
    cell_px = max(1, round(cell_m / resolution))
    inflate = max(1, math.ceil(robot_radius_m / (cell_px * resolution)))
    return build_grid(drivable, cell_px, inflate)


def plan_cell_sizes(
    resolution: float, cell_m: float = 0.25, robot_radius_m: float = 0.3
) -> list[int]:
    """Candidate planning cell sizes in pixels, coarsest first: from `cell_m` down to a
    quarter of the robot radius. Coarse cells plan fast on big maps; on a small map
    (nav2's 384 x 384 px sandboxes) a 0.25 m cell inflated by a whole cell leaves no
    corridor, while finer cells inflate by close to the real radius."""
    coarsest = max(1, round(cell_m / resolution))
    finest = max(1, min(coarsest, math.ceil(robot_radius_m / (4 * resolution))))
    return list(range(coarsest, finest - 1, -1))


def largest_component(ok: np.ndarray) -> np.ndarray:
    """The biggest 4-connected set of ok cells (stations go there so all are reachable).
    Components are found in row-major order of their first cell; on a tie in size the
    first found wins. A breadth-first search over a framed flat list (see `ok_padded`)."""
    _h, w = ok.shape
    pw = w + 2
    free = np.pad(ok, 1, constant_values=False).ravel().tolist()
    seen = [False] * len(free)
    best: list[int] = []
    steps = (pw, -pw, 1, -1)
    for r0, c0 in zip(*(a.tolist() for a in np.nonzero(ok))):
        first = (r0 + 1) * pw + c0 + 1
        if seen[first]:
            continue
        seen[first] = True
        component = [first]
        for node in component:  # the list grows while it is walked: a FIFO queue
            for d in steps:
                nxt = node + d
                if free[nxt] and not seen[nxt]:
                    seen[nxt] = True
                    component.append(nxt)
        if len(component) > len(best):
            best = component
    out = np.zeros(ok.shape, dtype=bool)
    if best:
        rows, cols = np.divmod(np.asarray(best), pw)
        out[rows - 1, cols - 1] = True
    return out


_SQRT2 = math.sqrt(2.0)
_STEPS = (
    (-1, 0, 1.0),
    (1, 0, 1.0),
    (0, -1, 1.0),
    (0, 1, 1.0),
    (-1, -1, _SQRT2),
    (-1, 1, _SQRT2),
    (1, -1, _SQRT2),
    (1, 1, _SQRT2),
)


def plan(grid: PlanGrid, start: Cell, goal: Cell) -> list[Cell] | None:
    """Shortest 8-connected path of ok cells from start to goal (both included), or None.

    A* with the octile heuristic; a diagonal step only where both cells beside it are ok
    (no corner cutting). Written over the grid's framed flat boolean list (`ok_padded`)
    with heapq rather than the `pathfinding` package's node objects: the same search at a
    fraction of the CPU, which is what lets the demo history simulate a week in well under a
    minute.
    """
    if not (grid.is_ok(start) and grid.is_ok(goal)):
        return None
    if start == goal:
        return [start]
    ok, pw = grid.ok_padded()
    gr, gc = goal
    target = (gr + 1) * pw + gc + 1
    origin = (start[0] + 1) * pw + start[1] + 1
    # (offset, cost, diagonal, the two side offsets a diagonal must find ok)
    moves = [(dr * pw + dc, step, bool(dr and dc), dc, dr * pw) for dr, dc, step in _STEPS]
    heuristic = _octile_heuristic(len(ok), pw, target)
    inf = math.inf
    best = [inf] * len(ok)
    best[origin] = 0.0
    came: dict[int, int] = {}
    frontier = [(0.0, 0.0, origin)]
    push, pop = heapq.heappush, heapq.heappop
    while frontier:
        _, cost, node = pop(frontier)
        if node == target:
            path = [node]
            while node in came:
                node = came[node]
                path.append(node)
            return [(n // pw - 1, n % pw - 1) for n in reversed(path)]
        if cost > best[node]:
            continue
        for offset, step, diagonal, side_a, side_b in moves:
            nxt = node + offset
            if not ok[nxt] or (diagonal and not (ok[node + side_a] and ok[node + side_b])):
                continue
            new_cost = cost + step
            if new_cost < best[nxt]:
                best[nxt] = new_cost
                came[nxt] = node
                push(frontier, (new_cost + heuristic[nxt], new_cost, nxt))
    return None


def _octile_heuristic(size: int, row_length: int, target: int) -> list[float]:
    """The octile distance from every cell of a framed flat grid to `target`, as a list by
    flat index: computed once per search with numpy rather than for every neighbour pushed.
    The same arithmetic in the same order as in Python (integers, then one float product
    and one sum), so the same floats."""
    index = np.arange(size)
    d_row = np.abs(index // row_length - target // row_length)
    d_col = np.abs(index % row_length - target % row_length)
    straight = (d_row + d_col).astype(np.float64)
    diagonal = np.minimum(d_row, d_col).astype(np.float64)
    table: list[float] = (straight + (_SQRT2 - 2) * diagonal).tolist()
    return table


def route_clear(grid: PlanGrid, cells: list[Cell] | np.ndarray) -> bool:
    """Whether a planned route is still drivable on `grid`: every cell ok, and no diagonal
    step cuts a corner (both cells beside it ok), as `plan` itself requires. `cells` may
    be an (n, 2) array already: the route cache keeps them so, made once per route."""
    if len(cells) == 0:
        return False
    at = np.asarray(cells)
    rows, cols = at[:, 0], at[:, 1]
    h, w = grid.shape
    if rows.min() < 0 or cols.min() < 0 or rows.max() >= h or cols.max() >= w:
        return False
    ok = grid.ok
    if not ok[rows, cols].all():
        return False
    # A diagonal step from (r0, c0) to (r1, c1) needs (r0, c1) and (r1, c0) ok too; on a
    # straight step those are the two cells themselves, already checked.
    return bool(ok[rows[:-1], cols[1:]].all() and ok[rows[1:], cols[:-1]].all())


def simplify(cells: list[Cell]) -> list[Cell]:
    """Drops the cells in the middle of straight runs (the path's shape does not change)."""
    if len(cells) <= 2:
        return list(cells)
    out = [cells[0]]
    for prev, cur, nxt in zip(cells, cells[1:], cells[2:]):
        if (cur[0] - prev[0], cur[1] - prev[1]) != (nxt[0] - cur[0], nxt[1] - cur[1]):
            out.append(cur)
    out.append(cells[-1])
    return out


def segment_pixels(a: tuple[float, float], b: tuple[float, float], step: float = 0.25):
    """Image pixels (col, row) a straight segment between two (u, v) points passes over."""
    (u0, v0), (u1, v1) = a, b
    n = max(1, int(math.hypot(u1 - u0, v1 - v0) / step))
    for i in range(n + 1):
        t = i / n
        yield int((u0 + (u1 - u0) * t) // 1), int((v0 + (v1 - v0) * t) // 1)


def path_is_clear(points: list[tuple[float, float]], drivable: np.ndarray) -> bool:
    """True when every pixel under the polyline is drivable."""
    h, w = drivable.shape
    pts = points if len(points) > 1 else points * 2
    for a, b in zip(pts, pts[1:]):
        for col, row in segment_pixels(a, b):
            if not (0 <= row < h and 0 <= col < w and drivable[row, col]):
                return False
    return True
