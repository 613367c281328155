"""The one harness of the gateway's fuzzers (2019 chunks and poses, VDA 5050 messages,
2019 command answers): the hostile values and payloads they generate, the mutation of a
good message, their budget, and the message handler (`Ingestor.handle`, in-process with the
in-memory publisher) with the checks every generated message must pass whatever it is:
acknowledged once, nothing left in flight, and either an accepted event or a dead letter
with a known reason that says why and keeps at most 64 KiB of the payload.

Where the time goes: a generated message costs Hypothesis about 5 ms of CPU to build (its
engine's bookkeeping per example and per drawn value: the recursive JSON values and the
mutation's choices) and the handler under 1 ms; nothing here is made per example."""

from __future__ import annotations

import functools
import json
from collections.abc import Sequence
from dataclasses import dataclass

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from mapservice.adapters.clock import ManualClock
from mapservice.core.events import DeadLetter, Envelope, decode, decode_dead_letter
from mapservice.core.wire2019 import Reason
from mapservice.ingest.gateway import Ingestor
from mapservice.settings import Settings
from mapservice.testing.memory_publisher import MemoryPublisher

# 2026-11-21T10:00:00Z, the gateway's clock in every fuzzer.
NOW = 1_795_255_200_000
REASONS = frozenset(r.value for r in Reason)
DEAD_LETTER_PAYLOAD_LIMIT = 64 * 1024


def budget(max_examples: int) -> settings:
    """A fuzzer's settings: `max_examples` generated messages, derandomized so a failure
    reproduces, no deadline (the machine is shared) and none of the health checks that
    hostile, sometimes huge, payloads trip by design."""
    return settings(
        max_examples=max_examples,
        deadline=None,
        derandomize=True,
        suppress_health_check=[
            HealthCheck.too_slow,
            HealthCheck.data_too_large,
            HealthCheck.filter_too_much,
        ],
    )


# --- what the fuzzers generate ----------------------------------------------------------

json_scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=False, allow_infinity=False),
    st.text(max_size=50),
    st.just("x" * 70_000),
    st.sampled_from(
        [
            "",
            "true",
            "NaN",
            "1e309",
            "\u0000",
            "\udcff".encode("utf-8", "surrogatepass").decode("utf-8", "replace"),
        ]
    ),
)
json_values = st.recursive(
    json_scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=10), inner, max_size=4)
    ),
    max_leaves=12,
)


# The strategies a mutation draws from, made once: a strategy made per draw is built and
# validated by Hypothesis again each time.
_REPEATS = st.integers(1, 4)
_ACTIONS = st.sampled_from(["replace", "drop", "add"])
_FIELD_NAMES = st.text(max_size=8)


@functools.cache
def _index_below(n: int) -> st.SearchStrategy[int]:
    return st.integers(0, n - 1)


@functools.cache
def _one_of_names(names: tuple[str, ...]) -> st.SearchStrategy[str]:
    return st.sampled_from(names)


def mutate(doc, draw, names: Sequence[str] = ()):
    """A copy of `doc` with a value replaced, dropped or added anywhere in it, in objects
    and arrays alike, one to four times. An added field is named by `names` (the fields a
    validator looks for) or by generated text."""
    doc = json.loads(json.dumps(doc))
    for _ in range(draw(_REPEATS)):
        parent, key, node = None, None, doc
        while isinstance(node, (dict, list)) and node and draw(st.booleans()):
            parent = node
            index = draw(_index_below(len(node)))
            key = sorted(node)[index] if isinstance(node, dict) else index
            node = node[key]
        action = draw(_ACTIONS)
        if parent is None or action == "add":
            target = (
                node if isinstance(node, (dict, list)) else parent if parent is not None else doc
            )
            if isinstance(target, dict):
                target[
                    draw(_one_of_names(tuple(names)))
                    if names and draw(st.booleans())
                    else draw(_FIELD_NAMES)
                ] = draw(json_values)
            elif isinstance(target, list):
                target.append(draw(json_values))
        elif action == "drop":
            parent.pop(key)
        else:
            parent[key] = draw(json_values)
    return doc


def raw_nasties(good: dict) -> st.SearchStrategy[bytes]:
    """Payloads that are not the message's JSON: random bytes (mostly invalid UTF-8),
    deep nesting, the good message cut short, its numbers made NaN, Infinity or out of
    range, and one over the size limit. The numbers replaced are a pose's 1.0 and 50."""
    text = json.dumps(good)
    return st.one_of(
        st.binary(max_size=300),
        st.integers(1, 5000).map(lambda n: b'{"x":' + b"[" * n + b"]" * n + b"}"),
        st.integers(0, len(text)).map(lambda n: text[:n].encode()),
        st.sampled_from(
            [
                text.replace("1.0", "NaN"),
                text.replace("1.0", "Infinity"),
                text.replace("1.0", "1e999"),
                text.replace("50", "-1e-400"),
            ]
        ).map(str.encode),
        st.just(b"{" + b'"a":1,' * 60_000 + b'"b":2}'),
    )


# --- the message handler and its checks -------------------------------------------------


@dataclass(frozen=True)
class Fate:
    """What became of one message: the event accepted, or the dead letter."""

    event: Envelope | None
    letter: DeadLetter | None

    @property
    def reason(self) -> str | None:
        return self.letter.reason if self.letter else None


class FuzzedGateway:
    """The gateway's message handler as the fuzzers drive it: one Ingestor for a whole
    module (its state after thousands of hostile messages is part of what is tested), or
    the one a test wired itself."""

    def __init__(
        self,
        gateway_id: str = "fuzz",
        *,
        wired: tuple[Settings, Ingestor, MemoryPublisher] | None = None,
    ) -> None:
        if wired is None:
            settings_, publisher = Settings(), MemoryPublisher()
            wired = (
                settings_,
                Ingestor(settings_, publisher, ManualClock(NOW), gateway_id=gateway_id),
                publisher,
            )
        self.settings, self.ingestor, self.publisher = wired

    def fate(self, topic: str, payload: bytes) -> Fate:
        """Handles one message and checks what every message must end as."""
        acked: list[int] = []
        record = self.ingestor.handle(topic, payload, lambda: acked.append(1))
        self.publisher.poll()
        assert acked == [1], "every message is acknowledged once Kafka has its record"
        assert self.ingestor.in_flight == 0
        if record.reason is None:
            return Fate(decode(record.value), None)
        assert record.topic == self.settings.topic_dead_letter and record.reason in REASONS
        letter = decode_dead_letter(record.value)
        assert letter.reason == record.reason
        assert len(letter.payload) <= DEAD_LETTER_PAYLOAD_LIMIT
        assert letter.detail, "a dead letter says why"
        return Fate(None, letter)
