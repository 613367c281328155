"""What the stack's Prometheus endpoints say during a run: the gateways' confirmed
messages, the store thread's stages and the history consumer's offset gaps.
"""

from __future__ import annotations

import httpx


def summed_samples(text: str, family_name: str, sample_name: str, key) -> dict:
    """One metric family's `sample_name` samples in a /metrics text, summed per
    `key(labels)`."""
    from prometheus_client.parser import text_string_to_metric_families

    out: dict = {}
    for family in text_string_to_metric_families(text):
        if family.name != family_name:
            continue
        for sample in family.samples:
            if sample.name == sample_name:
                k = key(sample.labels)
                out[k] = out.get(k, 0.0) + sample.value
    return out


def counter_by_label(text: str, counter: str, label: str) -> dict[str, float]:
    """A Prometheus counter's `<counter>_total` samples in a /metrics text, summed per value
    of one label (an unlabelled sample counts under "")."""
    return summed_samples(text, counter, f"{counter}_total", lambda labels: labels.get(label, ""))


def gateway_acks(health_ports: list[int]) -> list[float]:
    """Each gateway's messages handled and confirmed by Kafka so far (accepted and rejected,
    `mapservice_gateway_messages_total` on its health port's /metrics)."""
    counts = []
    for port in health_ports:
        text = httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=10).text
        counts.append(
            sum(counter_by_label(text, "mapservice_gateway_messages", "outcome").values())
        )
    return counts


# The server's store thread, stage by stage: each stage's histogram (one observation per
# call; batch_events observes each batch's size).
STORE_STAGES = {
    "insert": "mapservice_sink_insert_seconds",
    "conflicts_check": "mapservice_conflicts_check_seconds",
    "conflicts_write": "mapservice_conflicts_write_seconds",
    "derive_views": "mapservice_sink_derive_views_seconds",
    "batch_events": "mapservice_sink_batch_events",
}


def histogram_totals(text: str) -> dict[str, tuple[float, float]]:
    """The STORE_STAGES histograms' (count, sum) in a /metrics text (absent ones: 0, 0)."""
    from prometheus_client.parser import text_string_to_metric_families

    wanted = set(STORE_STAGES.values())
    out = dict.fromkeys(wanted, (0.0, 0.0))
    for family in text_string_to_metric_families(text):
        if family.name in wanted:
            count = sum(s.value for s in family.samples if s.name == f"{family.name}_count")
            total = sum(s.value for s in family.samples if s.name == f"{family.name}_sum")
            out[family.name] = (count, total)
    return out


def store_stages(
    before: dict[str, tuple[float, float]], after: dict[str, tuple[float, float]], wall_s: float
) -> dict:
    """What the store thread spent between two scrapes, per stage: calls, mean ms per call
    and its share of the wall time; and the batches' mean size in events."""
    out: dict = {}
    for stage, metric in STORE_STAGES.items():
        calls = after[metric][0] - before[metric][0]
        total = after[metric][1] - before[metric][1]
        if stage == "batch_events":
            out["batches"] = calls
            out["events_per_batch"] = total / calls if calls else None
        else:
            out[stage] = {
                "calls": calls,
                "mean_ms": 1000 * total / calls if calls else None,
                "busy_percent": 100 * total / wall_s if wall_s > 0 else None,
            }
    return out


def server_metrics(api_url: str) -> str:
    """The server's /metrics text: one scrape serves the store stages and the offset gaps."""
    return httpx.get(f"{api_url}/metrics", timeout=10).text


def history_offset_gaps(text: str) -> dict[str, float]:
    """The history consumer's offset gaps so far (`mapservice_consumer_offset_gaps_total` in
    the server's /metrics text): read again, or accepted as lost after its rereads ran out."""
    gaps = counter_by_label(text, "mapservice_consumer_offset_gaps", "outcome")
    return {"reread": gaps.get("reread", 0.0), "accepted": gaps.get("accepted", 0.0)}


# Publish -> stored, per event, as the server itself timed it: from the event's own
# timestamp (the load fleets stamp each message as they send it) to the return of the
# insert that made it queryable. Exact per event where the client's figures are bounds
# (the poll adds up to its interval, the push its Kafka hop), read at the histogram's
# bucket precision (25 ms steps up to 0.3 s).
STORED_LATENCY = "mapservice_event_to_stored_seconds"
# The same from the gateway's receive time: the part of publish -> stored after the MQTT
# broker and the gateway's queue (Kafka, the history consumer's batch and its insert).
RECEIVED_LATENCY = "mapservice_received_to_stored_seconds"


def histogram_buckets(text: str, metric: str = STORED_LATENCY) -> dict[float, float]:
    """A histogram's cumulative bucket counts in a /metrics text, by upper bound (`le`),
    summed over its other labels."""
    return summed_samples(text, metric, f"{metric}_bucket", lambda labels: float(labels["le"]))


def bucket_quantile(counts: dict[float, float], q: float) -> float | None:
    """The q-quantile (0..1) of cumulative bucket counts, linear within its bucket as
    Prometheus' histogram_quantile; None without observations. One in the +Inf bucket
    gives the highest finite bound (the quantile is at least that)."""
    bounds = sorted(counts)
    total = counts[bounds[-1]] if bounds else 0.0
    if total <= 0:
        return None
    rank = q * total
    lower, below = 0.0, 0.0
    for le in bounds:
        if counts[le] >= rank:
            if le == float("inf"):
                return lower
            inside = counts[le] - below
            return lower + (le - lower) * ((rank - below) / inside if inside else 1.0)
        lower, below = le, counts[le]
    return lower


def stored_latency(
    before: dict[float, float], after: dict[float, float], bound_s: float
) -> dict[str, float | None]:
    """Publish -> stored of the events stored between two scrapes: how many, p50 and p99
    (interpolated within their bucket), and the share stored within `bound_s` (exact when
    `bound_s` is a bucket bound)."""
    counts = {le: n - before.get(le, 0.0) for le, n in after.items()}
    total = counts.get(float("inf"), 0.0)
    within = max((n for le, n in counts.items() if le <= bound_s), default=0.0)
    return {
        "events": total,
        "p50_s": bucket_quantile(counts, 0.5),
        "p99_s": bucket_quantile(counts, 0.99),
        "within_bound_fraction": within / total if total else None,
    }
