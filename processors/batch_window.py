"""How long the history consumer collects a batch before storing it: a pure rule.

Every store of a batch has a fixed cost (on chDB ~25-45 ms: an insert per table and the
pose table's materialized views), whatever its size. Long windows amortise it; short
windows cut every event's wait. Which matters depends on the load, and the store's own
duration says which: at 1,000 robots a batch is stored in ~45 ms, and this rule took
~50 ms off the median latency and ~30 ms off the p99 for 14 % of a core; at 5,000 robots
a store takes ~100 ms and more, and there CPU is what the whole stack lacks (BENCHMARKS.md,
live ingest). So the window is sized to keep storing at STORE_SHARE of the loop's time: short while
stores are quick, growing to the longest window as they slow down (a busier machine makes
them slower too, so the loop backs off exactly when CPU gets scarce). It is also long enough
to gather FILL_EVENTS at the recent arrival rate, up to its own bound (the quiet window): a
quiet plant does not pay that fixed cost five times a second for a handful of events.

The fixed cost is not only the insert's. Each insert is a new part of every table it writes,
and ClickHouse merges a day's partition with its newest parts: while a partition is small (a
few MiB compressed, the first hours of a day at tens of robots) each merge rewrites the whole
of it, so the merging work of a quiet plant grows through the morning with every insert
(20 robots stored five times a second: `serve`'s merge threads from 3 % to 12 % of a core in
25 minutes). Fewer, fuller inserts cut that in proportion.
"""

from __future__ import annotations

STORE_SHARE = 0.4  # storing (insert, views, commit) takes at most this share of the loop
SMOOTHING = 0.3  # weight of the newest batch in the running store time
# A store's fixed cost is the same for 3 events as for 300: a small plant (20 robots send
# ~24 events a second) paid it ten times a second for a few events each, most of its
# processors' CPU. So the window is also long enough to gather about this many events at
# the recent arrival rate, within the same bounds: from about 400 robots (500 events a
# second) a plant gathers them within the shortest window and keeps it; a quiet one stores
# every longest window. (100 events, at 1,000 robots' 1,200 a second, lengthened windows
# whenever the rate dipped: the median publish -> stored rose by 25 ms.)
FILL_EVENTS = 50


def batch_window(
    store_s: float,
    shortest_s: float,
    longest_s: float,
    events_per_s: float | None = None,
    quiet_s: float | None = None,
) -> float:
    """The window that keeps a store of `store_s` at STORE_SHARE of the loop, within
    [shortest_s, longest_s] (a shortest beyond the longest is the longest), and gathers
    FILL_EVENTS at `events_per_s` (None: not known yet) within [shortest_s, quiet_s] (None:
    the longest). The store's rule keeps its own bound: a slow store under load never waits
    longer than `longest_s` for the sake of the quiet window."""
    floor = min(shortest_s, longest_s)
    window = min(longest_s, max(floor, store_s / STORE_SHARE))
    if events_per_s is not None:
        quiet = longest_s if quiet_s is None else quiet_s
        gather = FILL_EVENTS / events_per_s if events_per_s > 0 else quiet
        window = max(window, min(quiet, max(floor, gather)))
    return window


def smoothed(previous_s: float | None, sample_s: float) -> float:
    """The running store time after one more batch: one slow insert widens the window
    a little, a run of them widens it all the way."""
    if previous_s is None:
        return sample_s
    return previous_s + SMOOTHING * (sample_s - previous_s)
