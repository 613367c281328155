"""The fault tests' load counts each message in the segment its robot belongs to, even when
the test switches segments while a tick is being published (the switch comes from the test's
thread at any moment; a message counted under another segment's robot is looked for among
the wrong robots, and its fault never "catches up")."""

from __future__ import annotations

import time

from mapservice.adapters.ros_map import load_ros_map, meta_for
from tests.fixtures.mosquitto import mosquitto  # noqa: F401 (a fixture)
from tests.fixtures.paths import MAPS

from .fault_load import Load, Sent


def robot_of(sent: Sent) -> str:
    return sent.key[0] if sent.kind == "pose" else sent.key[2]


def test_each_message_is_counted_in_its_robot_s_segment_across_switches(mosquitto) -> None:  # noqa: F811
    load = Load(f"mqtt://127.0.0.1:{mosquitto}", meta_for(load_ros_map(MAPS / "depot.yaml")))
    try:
        publish = load.client.publish
        switches = iter(range(1_000_000))

        def publish_then_switch(*args, **kwargs):
            # The test's thread switching segments right after any publish: between a
            # tick's pose and its chunk, or between a tick's robot and its pose.
            info = publish(*args, **kwargs)
            load.segment = f"s{next(switches)}"
            return info

        load.client.publish = publish_then_switch  # type: ignore[method-assign]
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            sent = list(load.sent)
            if sum(1 for s in sent if s.kind == "chunk") >= 5:
                break
            time.sleep(0.05)
        load.stop()
    finally:
        load.close()
    sent = list(load.sent)
    assert sum(1 for s in sent if s.kind == "chunk") >= 5, "too few chunks published to judge"
    wrong = [s for s in sent if robot_of(s).rsplit("-", 1)[0] != s.segment]
    assert not wrong, f"{len(wrong)} of {len(sent)} counted in another robot's segment: {wrong[:3]}"
    assert all(s.acknowledged for s in sent)
