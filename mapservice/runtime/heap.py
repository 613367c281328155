"""The long-running processes' heap and Python's cyclic garbage collector.

A full (generation 2) collection walks every tracked object, and while it runs no other
thread of the process runs. At 5,000 robots these pauses took 0.1-0.3 s in the server and
0.05-0.12 s in the gateway, every few seconds: the largest part of the live latency's
tail (BENCHMARKS.md). Two measures keep them short: the event and row records are
msgspec structs with `gc=False` (frozen, immutable values: they cannot form cycles), and
what start-up built (modules, the app, settings: ~100,000 objects) is moved out of the
collector's sight once, here, since it lives as long as the process anyway.
"""

from __future__ import annotations

import gc


def freeze_startup_heap() -> int:
    """Collects once, then moves every object alive now to the permanent generation
    (`gc.freeze`): later collections skip them. Returns how many objects were frozen."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()
