"""librdkafka's own log lines through the service's structured logs.

Left alone, librdkafka writes its warnings (a broker it cannot reach, an idempotent
producer's id retried while a fresh broker loads) as raw `%4|1795866934.271|GETPID|…` lines
on stderr: no component, no level a log pipeline can read. Given a standard-library logger,
confluent-kafka hands each line to it instead, from the client's own poll() or flush()
(never from librdkafka's threads), and the logging setup renders it as every other record:
one JSON object in production, with `component`, `level` and `logger` = "librdkafka".

Only clients that poll get it: the lines wait for a poll, so an admin client (which is not
polled) would hold them unseen.
"""

from __future__ import annotations

import logging
from typing import Any

LIBRDKAFKA_LOGGER = logging.getLogger("librdkafka")


def logged(conf: dict[str, Any]) -> dict[str, Any]:
    """`conf` with librdkafka's log lines going to LIBRDKAFKA_LOGGER."""
    return {**conf, "logger": LIBRDKAFKA_LOGGER}
