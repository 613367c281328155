"""librdkafka's log lines reach the service's structured logs, not raw stderr."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from mapservice.adapters.kafka_batch_source import consumer_config
from mapservice.adapters.kafka_live_publisher import live_producer_config
from mapservice.adapters.kafka_live_relay import live_consumer_config
from mapservice.adapters.kafka_logs import LIBRDKAFKA_LOGGER
from mapservice.adapters.kafka_publisher import producer_config
from mapservice.settings import Settings

# A producer of the gateway's kind against a port nobody listens on, in a process whose
# logging is set up as a component's is (JSON lines).
PROBE = """
import time
from mapservice.runtime import logs
logs.configure(fmt="json", component="probe")
from mapservice.adapters.kafka_publisher import KafkaPublisher
from mapservice.settings import Settings
pub = KafkaPublisher(Settings(kafka_bootstrap="127.0.0.1:9"), "probe")
pub.publish("t", b"k", b"v", lambda error: None)
deadline = time.monotonic() + 3  # librdkafka retries a refused connect every ~50 ms
while time.monotonic() < deadline:
    pub.poll(0.2)
pub.close()
"""


def test_an_unreachable_broker_is_logged_as_json_lines_with_component_and_level() -> None:
    """Every line on stderr is one JSON object; librdkafka's refused connection is among
    them, as an error of the component, from the `librdkafka` logger."""
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert lines, "librdkafka logged nothing about a broker it cannot reach"
    raw = [line for line in lines if line.startswith("%")]
    assert not raw, f"raw librdkafka lines on stderr: {raw[:3]}"
    records = [json.loads(line) for line in lines]
    refused = [r for r in records if "Connection refused" in r["event"]]
    assert refused, records[:3]
    assert all(
        r["logger"] == "librdkafka" and r["component"] == "probe" and r["level"] == "error"
        for r in refused
    ), refused[:3]


@pytest.mark.parametrize(
    "config",
    [
        lambda s: producer_config(s, "gateway"),
        lambda s: live_producer_config(s, "live"),
        lambda s: consumer_config(s, "history"),
        live_consumer_config,
    ],
    ids=["producer", "live producer", "history consumer", "live relay"],
)
def test_every_polled_client_hands_its_lines_to_the_logger(config) -> None:
    assert config(Settings())["logger"] is LIBRDKAFKA_LOGGER
