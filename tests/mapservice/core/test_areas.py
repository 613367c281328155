"""Advertisement areas (core/areas.py): every chunk index, negative ones included, lies in
exactly the one area whose square of chunks holds it; a change goes to its area's topic
(and the 2019 one unless turned off); a connection's subscriptions are the union of its
robots' areas however they move."""

from __future__ import annotations

import random

import pytest

from mapservice.core.areas import (
    AdvertisementTopics,
    AreaGrid,
    AreaSubscriptions,
    area_topic,
    area_topic_filter,
)
from tests.fixtures.emqx_acl_eval import topic_matches


def squares(n: int, around: range) -> dict[tuple[int, int], set[tuple[int, int]]]:
    """The areas as squares of n x n chunks laid from chunk (0, 0), by enumeration."""
    tiles: dict[tuple[int, int], set[tuple[int, int]]] = {}
    for ar in range(around.start // n - 1, around.stop // n + 2):
        for ac in range(around.start // n - 1, around.stop // n + 2):
            tiles[(ar, ac)] = {
                (r, c) for r in range(ar * n, ar * n + n) for c in range(ac * n, ac * n + n)
            }
    return tiles


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7])
def test_every_chunk_lies_in_the_one_area_whose_square_holds_it(n: int) -> None:
    around = range(-3 * n - 2, 3 * n + 3)  # both sides of 0 and of several area edges
    tiles = squares(n, around)
    grid = AreaGrid(n)
    for row in around:
        for column in around:
            holding = [a for a, chunks in tiles.items() if (row, column) in chunks]
            assert holding == [grid.area_of_chunk(row, column)], (row, column)


def test_the_areas_of_a_block_of_chunks_are_those_of_its_chunks() -> None:
    rng = random.Random(3)
    for _ in range(500):
        grid = AreaGrid(rng.randint(1, 6))
        r0, c0 = rng.randint(-20, 20), rng.randint(-20, 20)
        rows, cols = range(r0, r0 + rng.randint(0, 15)), range(c0, c0 + rng.randint(0, 15))
        expected = {grid.area_of_chunk(r, c) for r in rows for c in cols}
        assert grid.areas_of_chunks(rows, cols) == expected


def test_an_area_is_at_least_one_chunk() -> None:
    for bad in (0, -1, -4):
        with pytest.raises(ValueError, match="at least 1 x 1"):
            AreaGrid(bad)


def test_a_change_goes_to_its_area_topic_and_the_2019_topic_unless_turned_off() -> None:
    rng = random.Random(5)
    for root in ("iot/chunks/advertisement", "site1/adverts/"):
        for _ in range(200):
            grid = AreaGrid(rng.randint(1, 5))
            row, column = rng.randint(-30, 30), rng.randint(-30, 30)
            area = grid.area_of_chunk(row, column)
            both = AdvertisementTopics(root, grid).for_chunk(row, column)
            only = AdvertisementTopics(root, grid, on_2019_topic=False).for_chunk(row, column)
            assert both == (root, area_topic(root, area)) and only == (area_topic(root, area),)
            topic = area_topic(root, area)
            assert topic == f"{root.rstrip('/')}/area/{area[0]}/{area[1]}"
            # Every area topic is under the filter robots may read; the 2019 topic is not,
            # and a 2019 robot's exact subscription never matches an area topic.
            assert topic_matches(area_topic_filter(root), topic)
            assert not topic_matches(area_topic_filter(root), root)
            assert not topic_matches(root, topic)


def test_the_subscriptions_are_the_union_of_the_robots_areas_as_they_move() -> None:
    """Random moves of a few robots sharing a connection: each move subscribes exactly the
    areas no robot read before and unsubscribes exactly those no robot reads now, so the
    broker's set (replayed from the moves) is always the union of the robots' areas."""
    rng = random.Random(11)
    for _ in range(50):
        subs = AreaSubscriptions()
        wanted: dict[str, frozenset] = {}
        at_broker: set = set()
        for _ in range(60):
            robot = f"r{rng.randint(0, 3)}"
            r, c = rng.randint(-3, 3), rng.randint(-3, 3)
            areas = frozenset(
                (r + dr, c + dc) for dr in range(rng.randint(0, 2)) for dc in range(2)
            )
            before = set().union(*wanted.values()) if wanted else set()
            gained, lost = subs.move(robot, areas)
            wanted[robot] = areas
            after = set().union(*wanted.values())
            assert gained == after - before and lost == before - after
            assert not gained & at_broker and lost <= at_broker
            at_broker = (at_broker | gained) - lost
            assert at_broker == after == set(subs.current())
            assert subs.of(robot) == areas
