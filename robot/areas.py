"""Which advertisement areas (core/areas.py) a robot reads, and a connection's subscriptions
that follow its robots as they move.

A robot reads the areas its surroundings touch: the square of its position plus a margin on
each side, clipped to the map (no chunk lies outside it, so no change is advertised there).
With the margin, a chunk changed near the robot reaches it before the robot is in it,
whatever side of an area's edge the robot is on.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Hashable, Iterable
from typing import Any

import paho.mqtt.client as mqtt

from mapservice.core.areas import (
    Area,
    AreaGrid,
    AreaSubscriptions,
    area_topic,
    area_topic_filter,
)
from mapservice.core.events import MapMetaSet

from .chunks import metres_to_pixel


def areas_of_pixel_window(
    col0: int, row0: int, col1: int, row1: int, meta: MapMetaSet, grid: AreaGrid
) -> frozenset[Area]:
    """The areas of the map's chunks holding any pixel of columns col0..col1 and rows
    row0..row1 (inclusive); the part outside the map touches none."""
    col0, col1 = max(col0, 0), min(col1, meta.width - 1)
    row0, row1 = max(row0, 0), min(row1, meta.height - 1)
    if col0 > col1 or row0 > row1:
        return frozenset()
    return grid.areas_of_chunks(
        range(row0 // meta.chunk_height, row1 // meta.chunk_height + 1),
        range(col0 // meta.chunk_width, col1 // meta.chunk_width + 1),
    )


def _margin(margin: float) -> float:
    if not margin >= 0:  # also NaN
        raise ValueError(f"the margin around a robot is 0 or more, not {margin}")
    return margin


def areas_around(
    x: float, y: float, margin_m: float, meta: MapMetaSet, grid: AreaGrid
) -> frozenset[Area]:
    """The areas of a robot at map point (x, y) metres, reading `margin_m` around it."""
    m = _margin(margin_m)
    col0, row0 = metres_to_pixel(x - m, y + m, meta)  # top left: rows grow downwards
    col1, row1 = metres_to_pixel(x + m, y - m, meta)
    return areas_of_pixel_window(col0, row0, col1, row1, meta, grid)


def areas_around_pixel(
    u: float, v: float, margin_px: float, meta: MapMetaSet, grid: AreaGrid
) -> frozenset[Area]:
    """As areas_around, at continuous image point (u = column, v = row) with the margin in
    pixels (the simulator's coordinates)."""
    m = _margin(margin_px)
    return areas_of_pixel_window(
        math.floor(u - m), math.floor(v - m), math.floor(u + m), math.floor(v + m), meta, grid
    )


def map_areas(meta: MapMetaSet, grid: AreaGrid) -> frozenset[Area]:
    """Every area of the map (a robot that does not know where it is yet)."""
    return areas_of_pixel_window(0, 0, meta.width - 1, meta.height - 1, meta, grid)


class AreaFeed:
    """One MQTT connection subscribed to the areas its robots need (their union), changed as
    they move: an area no robot needs any more is unsubscribed. Every area message goes to
    `on_message`; on a reconnect the areas needed then are subscribed again."""

    def __init__(
        self,
        client: mqtt.Client,
        advertisement_topic: str,
        on_message: Callable[..., None],
        qos: int = 1,
    ) -> None:
        self.client = client
        self.advertisement_topic = advertisement_topic
        self.qos = qos
        self.needed = AreaSubscriptions()
        self._lock = threading.Lock()  # moves (the robot's thread) vs reconnects (paho's)
        client.message_callback_add(area_topic_filter(advertisement_topic), on_message)
        previous = client.on_connect

        def on_connect(
            c: mqtt.Client,
            userdata: Any,
            flags: Any,
            reason_code: Any,
            properties: Any = None,
        ) -> None:
            if previous is not None:
                # paho's type names each version's signature; this client is of version 2
                previous(c, userdata, flags, reason_code, properties)  # type: ignore[call-arg]
            if not reason_code.is_failure:
                with self._lock:
                    self._subscribe(self.needed.current())

        client.on_connect = on_connect

    def topic(self, area: Area) -> str:
        return area_topic(self.advertisement_topic, area)

    def move(self, holder: Hashable, areas: Iterable[Area]) -> None:
        """`holder` (a robot) now needs `areas`; subscribes and unsubscribes the difference
        (while disconnected, the reconnect subscribes what is needed then)."""
        with self._lock:
            gained, lost = self.needed.move(holder, areas)
            if self.client.is_connected():
                if lost:
                    self.client.unsubscribe([self.topic(a) for a in sorted(lost)])
                self._subscribe(gained)

    def _subscribe(self, areas: Iterable[Area]) -> None:
        topics = [(self.topic(a), self.qos) for a in sorted(areas)]
        if topics:
            self.client.subscribe(topics)
