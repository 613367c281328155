"""The history consumer's group on Apache Kafka with each group protocol: a second member
joins, is killed (SIGKILL, no leave-group), and the survivor reads its partitions again
within a generous bound (bench/group_protocol.py measures the times)."""

from __future__ import annotations

import pytest

from mapservice.bench.group_protocol import member_loss

# Judges the group's rebalance times: alone on the machine.
pytestmark = pytest.mark.alone


@pytest.mark.timeout(240)
@pytest.mark.parametrize("protocol", ["classic", "consumer"])
def test_a_killed_member_s_partitions_are_read_again_by_the_survivor(
    apache_kafka, protocol
) -> None:
    """The broker's session timeout is 10 s for both protocols (the embedded node sets the
    consumer protocol's group.consumer.* to the classic members' values; Kafka's default
    is 45 s): recovery within 30 s, and the join moves half the partitions."""
    result = member_loss(apache_kafka, protocol, timeout_s=90)
    assert result["protocol"] == protocol
    assert 0 < result["join_s"] < 60
    # Not before the session timeout (nothing told the broker), and not long after it.
    assert 5 < result["reassigned_s"] <= result["recovered_s"] < 30
