"""Advertisement areas: the map's chunk grid coarsened into squares of `chunks` x `chunks`
chunks, each with an MQTT topic of its own, so a robot can read the map changes near it
instead of every change of the plant (the 2019 topic).

An area is keyed like a chunk, (area row, area column), row 0 at the top of the image:
chunk (row, column) lies in area (row // chunks, column // chunks). The areas tile the chunk
grid whatever the map (the processors need no map geometry to place a change), and floor
division keeps the tiling whole for any index a chunk write names.

Topics: `<advertisement topic>/area/<area row>/<area column>` next to the 2019 topic itself
(`iot/chunks/advertisement/area/0/3`). The 2019 topic is matched exactly by 2019 robots'
subscriptions, so the area topics below it never reach them.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Hashable, Iterable
from dataclasses import dataclass

# A robot near the middle of an area with a margin of a few metres reads 1 to 4 areas: with
# 100-pixel chunks, 4 chunks are 12 m at 3 cm a pixel and 20 m at 5 cm.
DEFAULT_AREA_CHUNKS = 4
# Metres around a robot whose areas it reads: enough to see a change a few seconds ahead
# at a robot's speed (1-2 m/s), small enough for 1 to 4 areas of the default size.
DEFAULT_AREA_MARGIN_M = 5.0
AREA_LEVEL = "area"

Area = tuple[int, int]  # (area row, area column)


@dataclass(frozen=True)
class AreaGrid:
    """Areas of `chunks` x `chunks` chunks."""

    chunks: int = DEFAULT_AREA_CHUNKS

    def __post_init__(self) -> None:
        if self.chunks < 1:
            raise ValueError(f"an area is at least 1 x 1 chunks, not {self.chunks}")

    def area_of_chunk(self, row: int, column: int) -> Area:
        return row // self.chunks, column // self.chunks

    def areas_of_chunks(self, rows: range, columns: range) -> frozenset[Area]:
        """The areas the chunks rows x columns touch (empty ranges: none)."""
        if not rows or not columns:
            return frozenset()
        r0, c0 = self.area_of_chunk(rows[0], columns[0])
        r1, c1 = self.area_of_chunk(rows[-1], columns[-1])
        return frozenset((r, c) for r in range(r0, r1 + 1) for c in range(c0, c1 + 1))


def area_topic_root(advertisement_topic: str) -> str:
    return f"{advertisement_topic.rstrip('/')}/{AREA_LEVEL}"


def area_topic(advertisement_topic: str, area: Area) -> str:
    return f"{area_topic_root(advertisement_topic)}/{area[0]}/{area[1]}"


def area_topic_filter(advertisement_topic: str) -> str:
    """The filter of every area's topic (what the broker lets robots read)."""
    return f"{area_topic_root(advertisement_topic)}/+/+"


@dataclass(frozen=True)
class AdvertisementTopics:
    """Where one chunk change is advertised: the 2019 topic (unless the plant has no 2019
    robot and turned it off) and the change's area topic."""

    advertisement_topic: str
    grid: AreaGrid = AreaGrid()
    on_2019_topic: bool = True

    def for_chunk(self, row: int, column: int) -> tuple[str, ...]:
        area = area_topic(self.advertisement_topic, self.grid.area_of_chunk(row, column))
        return (self.advertisement_topic, area) if self.on_2019_topic else (area,)


class AreaSubscriptions:
    """The areas a connection must read for the robots it carries: each robot (a holder)
    names the areas around it, the connection reads their union. `move` says which areas
    the union gained and lost, so only those are subscribed and unsubscribed."""

    def __init__(self) -> None:
        self._of: dict[Hashable, frozenset[Area]] = {}
        self._count: Counter[Area] = Counter()

    def move(self, holder: Hashable, areas: Iterable[Area]) -> tuple[set[Area], set[Area]]:
        """`holder` now needs `areas`: (areas to subscribe, areas to unsubscribe)."""
        new = frozenset(areas)
        old = self._of.get(holder, frozenset())
        if new == old:
            return set(), set()
        gained, lost = set(), set()
        for area in new - old:
            self._count[area] += 1
            if self._count[area] == 1:
                gained.add(area)
        for area in old - new:
            self._count[area] -= 1
            if self._count[area] == 0:
                del self._count[area]
                lost.add(area)
        if new:
            self._of[holder] = new
        else:
            self._of.pop(holder, None)
        return gained, lost

    def current(self) -> frozenset[Area]:
        """Every area some holder needs."""
        return frozenset(self._count)

    def of(self, holder: Hashable) -> frozenset[Area]:
        return self._of.get(holder, frozenset())
