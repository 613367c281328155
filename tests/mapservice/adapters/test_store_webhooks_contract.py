"""The store contract, webhooks (`WebhookRegistry`): the latest saved row of a webhook is
its own whatever the insert order, a removal hides it until it is saved again, the list's
order, and each replica's latest report per webhook replaces its earlier ones.

Every test runs over every store (memory, chDB, ClickHouse over HTTP) through the `store`
fixture of tests/conftest.py.
"""

from __future__ import annotations

import itertools

import msgspec
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapservice.core.webhook_registry import RegisteredWebhook, WebhookReport

_examples = itertools.count(1)  # the examples share the store: each reports later


def webhook(n: int, t0: int, **more) -> RegisteredWebhook:
    fields = {
        "webhook_id": f"wh-{n:016x}",
        "url": f"https://plant.example/hooks/{n}?q=a&b=c",
        "kinds": ("near_miss", "stuck"),
        "created_ms": t0 + n,
        "created_by": "operator",
    }
    return RegisteredWebhook(**{**fields, **more})


def test_a_saved_webhook_is_listed_as_saved_and_its_latest_row_wins(store, t0) -> None:
    one, two = webhook(2, t0, kinds=()), webhook(1, t0 + 5)
    store.save_webhook(two, two.created_ms)
    store.save_webhook(one, one.created_ms)
    assert store.webhooks() == [one, two]  # by creation, whatever the save order
    resumed = msgspec.structs.replace(one, resumed_ms=t0 + 100)
    store.save_webhook(resumed, t0 + 100)
    store.save_webhook(one, one.created_ms)  # an older row, saved after: not the webhook's
    assert store.webhooks() == [resumed, two]


def test_a_removed_webhook_is_left_out_until_saved_again(store, t0) -> None:
    one, two = webhook(1, t0), webhook(2, t0)
    store.save_webhook(one, t0)
    store.save_webhook(two, t0)
    store.remove_webhook(one.webhook_id, t0 + 10)
    assert store.webhooks() == [two]
    store.remove_webhook("wh-00000000000000ff", t0 + 10)  # unknown: nothing happens
    assert store.webhooks() == [two]
    store.save_webhook(one, t0 + 20)
    assert store.webhooks() == [one, two]


def test_on_a_tie_the_later_save_wins(store, t0) -> None:
    one = webhook(1, t0)
    store.save_webhook(one, t0 + 10)
    store.remove_webhook(one.webhook_id, t0 + 10)
    assert store.webhooks() == []


reports = st.lists(
    st.builds(
        WebhookReport,
        webhook_id=st.sampled_from(["wh-0000000000000001", "wh-0000000000000002"]),
        replica=st.sampled_from(["host-a:1", "host-b:2"]),
        reported_ms=st.integers(0, 10_000),
        paused_reason=st.sampled_from(["", "a delivery failed 6 tries in a row; last: HTTP 500"]),
        last_error=st.sampled_from(["", "HTTP 500", "ConnectError: refused"]),
        last_try_ms=st.integers(0, 10_000),
        last_result=st.sampled_from(["", "delivered", "HTTP 500"]),
        delivered=st.integers(0, 2**40),
        failed_tries=st.integers(0, 1000),
        dropped=st.integers(0, 1000),
        queued=st.integers(0, 10_000),
    ),
    max_size=8,
)


@settings(
    max_examples=5, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(batches=st.lists(reports, min_size=1, max_size=3))
def test_each_replicas_latest_report_per_webhook_stays(store, t0, batches) -> None:
    """Random reports in batches: read back, each (webhook, replica) has the one with the
    latest time (on a tie the later)."""
    base = t0 + 1_000_000 * next(_examples)
    expected = {}
    for batch in batches:
        batch = [msgspec.structs.replace(r, reported_ms=base + r.reported_ms) for r in batch]
        store.report_webhooks(batch)
        for r in batch:
            key = (r.webhook_id, r.replica)
            if key not in expected or r.reported_ms >= expected[key].reported_ms:
                expected[key] = r
    got = {(r.webhook_id, r.replica): r for r in store.webhook_reports()}
    for key, report in expected.items():
        assert got[key] == report
    assert list(got) == sorted(got)
