"""A webhook's state over the processors replicas (mapservice/core/webhook_registry.py):
paused when a replica that reported lately is, the latest try, the counts summed; a report
just past the freshness is a replica gone and counts for nothing. Checked on generated
reports against a brute-force fold."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from mapservice.core.webhook_registry import WebhookReport, combined_state

NOW, FRESH = 1_000_000, 60_000

reports = st.lists(
    st.builds(
        WebhookReport,
        webhook_id=st.just("wh-0000000000000001"),
        replica=st.text("abc", min_size=1, max_size=3),
        # just inside and just outside the freshness, and anywhere
        reported_ms=st.sampled_from([NOW, NOW - FRESH, NOW - FRESH - 1, 0]) | st.integers(0, NOW),
        paused_reason=st.sampled_from(["", "a delivery failed 6 tries in a row; last: HTTP 500"]),
        last_error=st.sampled_from(["", "HTTP 500", "ConnectError: refused"]),
        last_try_ms=st.integers(0, NOW),
        last_result=st.sampled_from(["", "delivered", "HTTP 500"]),
        delivered=st.integers(0, 10**9),
        failed_tries=st.integers(0, 10**6),
        dropped=st.integers(0, 10**6),
        queued=st.integers(0, 10**4),
    ),
    max_size=6,
)


@given(reports)
def test_the_state_folds_the_fresh_reports_only(rows) -> None:
    state = combined_state(rows, NOW, FRESH)
    fresh = [r for r in rows if NOW - r.reported_ms <= FRESH]
    assert state.replicas == len(fresh)
    assert (state.state == "paused") == any(r.paused_reason for r in fresh)
    assert (state.paused_reason != "") == (state.state == "paused")
    assert state.delivered == sum(r.delivered for r in fresh)
    assert state.failed_tries == sum(r.failed_tries for r in fresh)
    assert state.dropped == sum(r.dropped for r in fresh)
    assert state.queued == sum(r.queued for r in fresh)
    latest = max((r.last_try_ms for r in fresh), default=0)
    assert state.last_try_ms == (latest or None)
    if fresh:
        assert state.last_result in {r.last_result for r in fresh if r.last_try_ms == latest}
    errors = [r for r in fresh if r.last_error]
    if errors:
        newest = max(r.last_try_ms for r in errors)
        assert state.last_error in {r.last_error for r in errors if r.last_try_ms == newest}
    else:
        assert state.last_error == ""


def test_nothing_reported_is_active_with_no_try() -> None:
    state = combined_state([], NOW, FRESH)
    assert (state.state, state.last_try_ms, state.replicas, state.delivered) == (
        "active",
        None,
        0,
        0,
    )
