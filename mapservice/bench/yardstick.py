"""A fixed CPU yardstick: how fast this machine does one set piece of work right now.

This VM's speed drifts by half from hour to hour, and latency at a given load follows it.
`bench ingest` measures the yardstick just before each run's stack starts (the machine
otherwise as quiet as the run will find it), so runs of different hours or days can be
compared knowing whether the machine was the same one.
"""

from __future__ import annotations

import statistics
import time
import zlib
from collections.abc import Callable

import msgspec

# One robot's pose message, as the pipeline decodes, re-encodes and compresses them.
_POSE = {
    "robot_id": "yardstick-0001",
    "timestamp": 1_795_255_200_000,
    "position": [12.5, -3.25, 0.0],
    "orientation": [0.0, 0.0, 0.3826834, 0.9238795],
    "battery_level": 81.5,
    "charging": False,
    "loaded": True,
    "path": [[float(i), float(i) / 2] for i in range(20)],
}
_ENCODED = msgspec.json.encode(_POSE)
_PIXELS = bytes(range(256)) * 160  # 40 KiB: a map chunk's order of size


def _one_round() -> int:
    """The set piece: JSON decode/encode, Python-level arithmetic and zlib, in the mix the
    pipeline spends its CPU on. Returns a checksum so nothing can be skipped."""
    total = 0
    for i in range(2000):
        pose = msgspec.json.decode(_ENCODED)
        pose["timestamp"] += i
        total += len(msgspec.json.encode(pose))
        x, y = pose["position"][0], pose["position"][1]
        total += int(x * 1000 + y * 1000) % 7
    total += len(zlib.compress(_PIXELS, 6))
    return total


def yardstick_ms(rounds: int = 9, clock: Callable[[], float] = time.perf_counter) -> float:
    """Median wall milliseconds of one round of the set piece (lower is faster); wall time,
    not CPU time, so a hypervisor taking the core away shows too."""
    if rounds < 1:
        raise ValueError("rounds must be at least 1")
    _one_round()  # warm-up: imports, allocator, caches
    times = []
    for _ in range(rounds):
        t0 = clock()
        _one_round()
        times.append((clock() - t0) * 1000)
    return statistics.median(times)
