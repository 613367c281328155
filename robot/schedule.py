"""When a simulated robot sends its chunk: the 2019 workload's one chunk every five poses.

Each robot's chunks are offset by its index in the fleet, so a fleet's chunks spread evenly
over the chunk period, as those of robots started at different moments do. Were every robot
to send its chunk after the same pose, the whole fleet's chunks would fall into one second
of every five: at 5,000 robots 10,000 events/s in that second and 5,000 in the four after
it, not a steady 6,000 (the load fleet did so once, and its latency figures measured the
burst: docs/benchmarks-journal.md). `aligned` keeps that burst schedule for stress runs.
"""

from __future__ import annotations


def chunk_phase(index: int, per_chunk: int, aligned: bool = False) -> int:
    """How many poses robot `index`'s chunk cycle is ahead of robot 0's (0 when aligned)."""
    return 0 if aligned else index % per_chunk


def chunk_follows(pose_number: int, phase: int, per_chunk: int) -> bool:
    """Whether a robot's `pose_number`-th pose (counted from 1) is followed by a chunk."""
    return (pose_number + phase) % per_chunk == 0


def chunks_after(poses: int, phase: int, per_chunk: int) -> int:
    """How many chunks a robot sends along with its first `poses` poses."""
    return (poses + phase) // per_chunk
