"""The long-running processes' heap and Python's cyclic garbage collector.

A full (generation 2) collection walks every tracked object, and while it runs no other
thread of the process runs. At 5,000 robots these pauses took 0.1-0.3 s in the server and
0.05-0.12 s in the gateway, every few seconds: the largest part of the live latency's
tail (BENCHMARKS.md). Two measures keep them short: the event and row records are
msgspec structs with `gc=False` (frozen, immutable values: they cannot form cycles), and
what start-up built (modules, the app, settings: ~100,000 objects) is moved out of the
collector's sight once, here, since it lives as long as the process anyway.

And collections run less often (`COLLECT_AFTER`). With Python's default of one young
collection per 700 more allocations than frees, the server, which holds a second of
events between batches, ran ~90 young, 8 middle and nearly one full collection a second
at 5,000 robots: 4-6 % of a core, each full one a 25-32 ms pause of every thread. With
10,000: three young collections a second and one full one a minute (BENCHMARKS.md).
"""

from __future__ import annotations

import gc

# gc.set_threshold(young, middle, full): a young collection once allocations exceed frees
# by 10,000 objects (default 700), the others as by default after 10 of the one below.
COLLECT_AFTER = (10_000, 10, 10)


def freeze_startup_heap() -> int:
    """Collects once, then moves every object alive now to the permanent generation
    (`gc.freeze`): later collections skip them; and collects less often from now on
    (COLLECT_AFTER). Returns how many objects were frozen."""
    gc.collect()
    gc.freeze()
    gc.set_threshold(*COLLECT_AFTER)
    return gc.get_freeze_count()
