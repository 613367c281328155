"""`mapservice bench fanout`: how many messages the broker sends for the map's changes, on
the 2019 topic (every robot reads every change) and on the area topics (each robot reads
the areas around it, core/areas.py and robot/areas.py), over a simulated shift.

The shift is the simulator's step function (robot/sim.py, no broker, no clock): after each
step every robot reads the areas around where it is, and each chunk a floor change wrote
goes to the robots reading its area. The advertisement's size is that of the processors'
payload (core/liveview.py) for each changed chunk, encoded as the advertiser encodes it.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import statistics
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import msgspec

from mapservice.core.areas import DEFAULT_AREA_CHUNKS, DEFAULT_AREA_MARGIN_M, AreaGrid
from mapservice.core.events import ChunkUpdated, make_envelope
from mapservice.robot import DEFAULT_MAP

if TYPE_CHECKING:
    from mapservice.robot.sim_model import ChunkOut, SimState

_json = msgspec.json.Encoder()


@dataclass(frozen=True)
class FanOut:
    robots: int
    simulated_s: int
    changes: int  # chunk changes advertised
    sent_2019: int  # messages out of the broker on the 2019 topic
    sent_areas: int  # messages out on the area topics
    max_readers: int  # the most robots one change reached on its area's topic
    areas_read_mean: float  # areas a robot reads, over robots and steps
    advertisement_bytes_mean: float

    @property
    def ratio(self) -> float:
        """Messages on the area topics over those on the 2019 topic."""
        return self.sent_areas / self.sent_2019 if self.sent_2019 else 0.0


def advertisement_bytes(state: SimState, chunk: ChunkOut) -> int:
    from mapservice.core.liveview import advertisement

    meta = state.meta
    payload = ChunkUpdated(
        chunk.row,
        chunk.column,
        meta.chunk_width,
        meta.chunk_height,
        zlib.compress(chunk.pixels),
        hashlib.blake2b(chunk.pixels, digest_size=16).digest(),
    )
    envelope = make_envelope(chunk.robot_id, chunk.t_ms, chunk.t_ms, payload)
    return len(_json.encode(advertisement(envelope, "http://127.0.0.1:8080")))


def run(
    map_yaml: Path,
    robots: int,
    seconds: int,
    *,
    grid: AreaGrid = AreaGrid(),
    margin_m: float = DEFAULT_AREA_MARGIN_M,
    change_every_s: float = 20.0,
    seed: int = 7,
) -> FanOut:
    from mapservice.adapters.ros_map import load_ros_map
    from mapservice.robot.areas import areas_around_pixel
    from mapservice.robot.sim import SimConfig, new_state, step

    ros_map = load_ros_map(map_yaml)
    state = new_state(ros_map, robots, seed=seed, config=SimConfig(change_every_s=change_every_s))
    margin_px = margin_m / ros_map.resolution
    n = len(state.robots)
    changes = sent_areas = max_readers = read_total = 0
    sizes: list[int] = []
    for _ in range(seconds):
        state, out = step(state)
        around = [areas_around_pixel(*r.pos, margin_px, state.meta, grid) for r in state.robots]
        read_total += sum(len(a) for a in around)
        for chunk in out.chunks:
            area = grid.area_of_chunk(chunk.row, chunk.column)
            readers = sum(area in a for a in around)
            changes += 1
            sent_areas += readers
            max_readers = max(max_readers, readers)
            sizes.append(advertisement_bytes(state, chunk))
    return FanOut(
        robots=n,
        simulated_s=seconds,
        changes=changes,
        sent_2019=changes * n,
        sent_areas=sent_areas,
        max_readers=max_readers,
        areas_read_mean=read_total / max(n * seconds, 1),
        advertisement_bytes_mean=statistics.mean(sizes) if sizes else 0.0,
    )


def main(args: argparse.Namespace) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console()
    grid = AreaGrid(args.area_chunks)
    table = Table(title=f"advertisement fan-out, {args.map}, {args.seconds} simulated s")
    for column in (
        "robots",
        "chunk changes",
        "2019 topic: messages out",
        "area topics: messages out",
        "area / 2019",
        "most readers of a change",
        "areas a robot reads",
        "advertisement bytes",
    ):
        table.add_column(column, justify="right")
    results = []
    for robots in args.robots:
        r = run(
            Path(args.map),
            robots,
            args.seconds,
            grid=grid,
            margin_m=args.area_margin,
            change_every_s=args.change_every,
            seed=args.seed,
        )
        results.append({**asdict(r), "ratio": r.ratio})
        table.add_row(
            str(r.robots),
            str(r.changes),
            f"{r.sent_2019:,}",
            f"{r.sent_areas:,}",
            f"{r.ratio:.3f}",
            str(r.max_readers),
            f"{r.areas_read_mean:.2f}",
            f"{r.advertisement_bytes_mean:,.0f}",
        )
    console.print(table)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
        console.print(f"wrote {args.json}")


def add_parser(kinds: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    bench = kinds.add_parser(
        "fanout",
        help="messages the broker sends for the map's changes: the 2019 topic against the "
        "per-area topics, over a simulated shift",
    )
    bench.add_argument(
        "--robots", type=int, nargs="+", default=[20, 100], help="fleet sizes to run"
    )
    bench.add_argument("--seconds", type=int, default=600, help="simulated seconds per run")
    bench.add_argument("--map", default=str(DEFAULT_MAP), help="ROS map YAML of the shift")
    bench.add_argument(
        "--area-chunks", type=int, default=DEFAULT_AREA_CHUNKS, help="side of an area in chunks"
    )
    bench.add_argument(
        "--area-margin",
        type=float,
        default=DEFAULT_AREA_MARGIN_M,
        help="metres around a robot whose areas it reads",
    )
    bench.add_argument(
        "--change-every",
        type=float,
        default=20.0,
        help="mean seconds between floor changes (the simulator's default)",
    )
    bench.add_argument("--seed", type=int, default=7, help="the shift's random seed")
    bench.add_argument("--json", default=None, help="write the runs as JSON to this file")
    bench.set_defaults(func=main)
