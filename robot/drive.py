"""`mapservice drive`: one robot driven from the terminal (the 2019 interactive simulator).

Arrow keys move the robot one screen cell (`--step` pixels); b, g and w paint the whole
chunk under it black (occupied), grey (unknown) or white (free), and the chunk is
published on iot/chunks/create like any robot's map update. The pose goes out on every
move and once a second, on iot/coordinates/{robotId}.
"""

from __future__ import annotations

import argparse
import curses
import sys
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from mapservice.adapters.ros_map import RosMap, drivable, load_ros_map, meta_for
from mapservice.core.events import MapMetaSet
from mapservice.core.wire2019 import encode_chunk_create, encode_coordinates, format_timestamp

from .chunks import chunk_of_pixel, chunk_pixels, metres_to_pixel, paste_chunk, pixel_to_metres
from .connection import RobotMqtt, robot_mqtt_from_args
from .faults import yaw_quaternion

if TYPE_CHECKING:
    import httpx

MOVES = {"up": (0, -1), "down": (0, 1), "left": (-1, 0), "right": (1, 0)}
YAWS = {"up": np.pi / 2, "down": -np.pi / 2, "left": np.pi, "right": 0.0}


@dataclass(frozen=True)
class DriveState:
    ros_map: RosMap
    meta: MapMetaSet
    col: int
    row: int
    yaw: float = 0.0
    step: int = 10
    note: str = ""

    def metres(self) -> tuple[float, float]:
        x, y = pixel_to_metres(self.col, self.row, self.meta)
        return round(x, 3), round(y, 3)

    def chunk(self) -> tuple[int, int]:
        return chunk_of_pixel(self.col, self.row, self.meta)


def start_state(
    ros_map: RosMap, start: tuple[float, float] | None = None, step: int = 10
) -> DriveState:
    meta = meta_for(ros_map)
    if start is not None:
        col, row = metres_to_pixel(*start, meta)
        if not (0 <= col < ros_map.width and 0 <= row < ros_map.height):
            raise ValueError(f"start {start} m lies outside the map")
    else:  # the free pixel nearest the middle of the map
        rows, cols = np.nonzero(drivable(ros_map))
        i = int(np.argmin((rows - ros_map.height / 2) ** 2 + (cols - ros_map.width / 2) ** 2))
        row, col = int(rows[i]), int(cols[i])
    return DriveState(ros_map, meta, col, row, step=step)


def move(state: DriveState, direction: str) -> DriveState:
    """One step; a robot does not drive into a wall (or off the map)."""
    dc, dr = MOVES[direction]
    col, row = state.col + dc * state.step, state.row + dr * state.step
    m = state.ros_map
    if not (0 <= col < m.width and 0 <= row < m.height):
        return replace(state, yaw=YAWS[direction], note="edge of the map")
    lo_r, hi_r = sorted((state.row, row))
    lo_c, hi_c = sorted((state.col, col))
    if not drivable(replace(m, pixels=m.pixels[lo_r : hi_r + 1, lo_c : hi_c + 1])).all():
        return replace(state, yaw=YAWS[direction], note="blocked")
    return replace(state, col=col, row=row, yaw=YAWS[direction], note="")


def paint(state: DriveState, colour: str) -> tuple[DriveState, int, int, bytes]:
    """Fills the chunk under the robot; returns the new state and the chunk to publish."""
    m = state.ros_map
    value = {
        "black": 255 if m.negate else 0,
        "white": 0 if m.negate else 254,
        "grey": m.unknown_value,
    }[colour]
    row, column = state.chunk()
    data = bytes([value]) * (state.meta.chunk_width * state.meta.chunk_height)
    pixels = m.pixels.copy()
    paste_chunk(pixels, state.meta, row, column, data)
    new = replace(
        state, ros_map=m.with_pixels(pixels), note=f"painted chunk ({row}, {column}) {colour}"
    )
    return new, row, column, chunk_pixels(pixels, state.meta, row, column, m.unknown_value)


def render(state: DriveState, rows: int, cols: int) -> list[str]:
    """The map around the robot, one character per step x step block: '#' occupied,
    ' ' free, ':' unknown, '@' the robot, '+' chunk corners."""
    m, s = state.ros_map, state.step
    free = drivable(m)
    occupied = m.pixels == (255 if m.negate else 0)
    top, left = state.row - (rows // 2) * s, state.col - (cols // 2) * s
    lines = []
    for i in range(rows):
        chars = []
        for j in range(cols):
            r0, c0 = top + i * s, left + j * s
            if r0 < 0 or c0 < 0 or r0 >= m.height or c0 >= m.width:
                chars.append("~")
                continue
            if i == rows // 2 and j == cols // 2:
                chars.append("@")
            elif occupied[r0 : r0 + s, c0 : c0 + s].any():
                chars.append("#")
            elif free[r0 : r0 + s, c0 : c0 + s].all():
                on_corner = r0 % state.meta.chunk_height < s and c0 % state.meta.chunk_width < s
                chars.append("+" if on_corner else " ")
            else:
                chars.append(":")
        lines.append("".join(chars))
    return lines


class Publisher:
    def __init__(self, mqtt_url: str, robot_id: str, mqtt_conn: RobotMqtt | None = None) -> None:
        self.robot_id = robot_id
        self.conn = mqtt_conn or RobotMqtt(mqtt_url)  # its own credential, if it has one
        self.client = self.conn.client(f"drive-{robot_id}", robot_id)
        self.conn.connect(self.client, who=f"robot {robot_id}")
        self.poses = self.chunks = 0

    def pose(self, state: DriveState) -> None:
        x, y = state.metres()
        now = time.time_ns() // 1_000_000
        self.client.publish(
            f"iot/coordinates/{self.robot_id}",
            encode_coordinates(
                self.robot_id, format_timestamp(now), x, y, yaw_quaternion(state.yaw)
            ),
            qos=1,
        )
        self.poses += 1

    def chunk(self, row: int, column: int, data: bytes) -> None:
        now = time.time_ns() // 1_000_000
        self.client.publish(
            self.conn.chunk_topic(self.robot_id),
            encode_chunk_create(row, column, data, format_timestamp(now), self.robot_id),
            qos=1,
        )
        self.chunks += 1

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


KEYS = {
    curses.KEY_UP: "up",
    curses.KEY_DOWN: "down",
    curses.KEY_LEFT: "left",
    curses.KEY_RIGHT: "right",
}
PAINT = {ord("b"): "black", ord("g"): "grey", ord("w"): "white"}


def _loop(screen: curses.window, state: DriveState, pub: Publisher) -> None:
    curses.curs_set(0)
    screen.keypad(True)
    screen.timeout(200)
    last_pose = 0.0
    while True:
        height, width = screen.getmaxyx()
        screen.erase()
        for i, line in enumerate(render(state, max(height - 3, 1), max(width - 1, 1))):
            screen.addstr(i, 0, line)
        x, y = state.metres()
        row, column = state.chunk()
        status = (
            f"{pub.robot_id}  x={x:.2f} y={y:.2f} m  chunk ({row}, {column})  "
            f"sent {pub.poses} poses {pub.chunks} chunks"
        )
        help_line = "arrows: drive  b/g/w: paint chunk black/grey/white  q: quit"
        screen.addstr(max(height - 2, 0), 0, status[: width - 1], curses.A_BOLD)
        screen.addstr(
            max(height - 1, 0),
            0,
            (f"{state.note}  |  {help_line}" if state.note else help_line)[: width - 1],
        )
        screen.refresh()
        key = screen.getch()
        if key in (ord("q"), 27):
            return
        if key in KEYS:
            state = move(state, KEYS[key])
            pub.pose(state)
            last_pose = time.monotonic()
        elif key in PAINT:
            state, r, c, data = paint(state, PAINT[key])
            pub.chunk(r, c, data)
        if time.monotonic() - last_pose >= 1.0:  # status once a second, as robots do
            pub.pose(state)
            last_pose = time.monotonic()


def check_map_size(
    api_url: str, meta: MapMetaSet, http: httpx.Client | None = None, token: str | None = None
) -> None:
    """Raises ValueError when the service stores a map of another size: painting this map's
    chunks into it would corrupt it (a service without a map accepts any)."""
    import httpx

    from mapservice.robot.map_upload import mismatch_message, same_geometry, stored_meta

    try:
        if http is not None:
            stored = stored_meta(http)
        else:
            from .api_client import api_client

            with api_client(api_url, token, timeout=10) as client:
                stored = stored_meta(client)
    except httpx.HTTPError as exc:
        raise ValueError(
            f"cannot ask {api_url} for the service's map size ({exc}); "
            "pass the service's REST API with --api"
        ) from exc
    if stored is not None and not same_geometry(stored, meta):
        raise ValueError(mismatch_message(stored, meta, f"this map ({meta.width} x {meta.height})"))


def main(args: argparse.Namespace) -> None:
    try:
        ros_map = load_ros_map(args.map)
        state = start_state(ros_map, tuple(args.start) if args.start else None, args.step)
        if not args.no_size_check:
            from .api_client import writer_token

            check_map_size(args.api, state.meta, token=writer_token(args.token))
        pub = Publisher(args.mqtt, args.robot_id, robot_mqtt_from_args(args, args.mqtt))
    except (OSError, ValueError) as exc:
        sys.exit(f"mapservice drive: {exc}")
    try:
        curses.wrapper(_loop, state, pub)
    except KeyboardInterrupt:
        pass
    finally:
        pub.close()
