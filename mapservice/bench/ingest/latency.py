"""Publish -> queryable per event, from the probes' notes: bounds, stages and percentiles."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from mapservice.bench.ingest.probes import Key

INF = float("inf")


def queryable_times(first_polled: dict[Key, float], pushed: dict[Key, float]) -> dict[Key, float]:
    """Per event, the earliest moment it is known to be queryable: the end of the first
    poll that returned it or the sending of its live push, whichever came first."""
    out = dict(first_polled)
    for key, at in pushed.items():
        if at < out.get(key, INF):
            out[key] = at
    return out


def _latencies(
    queryable_at: dict[Key, float], not_seen_at: dict[Key, float], keys: dict[Key, float]
) -> tuple[list[float], list[float]]:
    """Per published event: (upper, lower) bound of publish -> queryable, in seconds.

    Upper: the first moment it was known queryable (`queryable_times`; for a polled event
    that includes up to one poll interval and the poll's own duration). Lower: the start
    of the last poll that did not return it. Events never seen inside the 30 s window
    count as infinite, so they push the percentiles up instead of vanishing from them.
    """
    upper, lower = [], []
    for key, wall in keys.items():
        seen = queryable_at.get(key)
        if seen is None:
            upper.append(INF)
            lower.append(INF)
        else:
            upper.append(seen - wall)
            lower.append(min(seen - wall, max(0.0, not_seen_at.get(key, wall) - wall)))
    return upper, lower


def _stage_latencies(
    received_at: dict[Key, float], queryable_at: dict[Key, float], keys: dict[Key, float]
) -> dict[str, Any]:
    """Where the time goes, per event seen: publish -> gateway receive (Mosquitto, the
    gateway's MQTT client) and gateway receive -> queryable (Kafka produce, tansu, the
    history consumer, the insert, the push or poll)."""
    to_gateway, after_gateway = [], []
    for key, wall in keys.items():
        received = received_at.get(key)
        if received is not None and key in queryable_at:
            # The gateway stamps whole milliseconds (floored); floor the publish time the
            # same way, or a sub-millisecond hop comes out negative.
            to_gateway.append(received - math.floor(wall * 1000) / 1000)
            after_gateway.append(queryable_at[key] - received)
    return {
        "publish_to_gateway_p50_s": _pct(to_gateway, 50),
        "publish_to_gateway_p99_s": _pct(to_gateway, 99),
        "gateway_to_queryable_p50_s": _pct(after_gateway, 50),
        "gateway_to_queryable_p99_s": _pct(after_gateway, 99),
    }


def _pct(values: Sequence[float], q: float) -> float | None:
    if not values:
        return None
    s = sorted(values)  # nearest rank: the smallest value with q % of the values at or below it
    return s[min(len(s) - 1, max(0, math.ceil(q / 100.0 * len(s)) - 1))]
