"""The gateway's Prometheus metrics."""

from prometheus_client import Counter, Gauge, Histogram

MESSAGES = Counter("mapservice_gateway_messages_total", "MQTT messages handled", ["outcome"])
# Each outcome's series, looked up once: `labels()` costs ~3 µs, paid per message.
OUTCOMES = {outcome: MESSAGES.labels(outcome) for outcome in ("accepted", "rejected")}
REJECTED = Counter(
    "mapservice_gateway_rejected_total", "Messages sent to the dead-letter topic", ["reason"]
)
DELIVERY_FAILURES = Counter(
    "mapservice_gateway_delivery_failures_total", "Kafka deliveries that failed and were retried"
)
HANDLING_ERRORS = Counter(
    "mapservice_gateway_handling_errors_total",
    "Messages whose handling failed unexpectedly (left unacknowledged)",
)
IN_FLIGHT = Gauge("mapservice_gateway_in_flight", "MQTT messages awaiting Kafka confirmation")
MQTT_CONNECTED = Gauge(
    "mapservice_gateway_mqtt_connected", "1 while the gateway's MQTT session is up"
)
ACK_LATENCY = Histogram(
    "mapservice_gateway_ack_seconds",
    "MQTT receive to Kafka-confirmed ack",
    buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5),
)


def _preinitialise() -> None:
    """A series for every dead-letter reason from the start: a rate() over a reason that
    has not happened yet is 0, not missing, and the dashboard lists every reason."""
    from mapservice.core.wire2019 import Reason

    for reason in Reason:
        REJECTED.labels(reason.value)


_preinitialise()
