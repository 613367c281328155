"""The latency probes: a poller of the API and a listener on its live WebSocket note when
each published event was first known queryable; `DrainWatch` decides when the drain
after the fleet stops is over.
"""

from __future__ import annotations

import json
import threading
import time
from typing import Any

import httpx

KEYS_PER_POSE = "pose"
KEYS_PER_CHUNK = "chunk"


POLL_INTERVAL_S = 0.1
MAX_WINDOW_MS = 30_000  # the sliding window never reaches further back than this


POLL_LIMIT = 10_000  # rows per poll and kind: bounds the poller's read load while lagging
DRAIN_STALL_S = 20.0  # the drain ends when the store has counted nothing new for this long
DRAIN_MAX_S = 600.0  # and in any case after this long


Key = tuple[str, str, int]  # (kind, robot id, event time ms)


class QueryablePoller(threading.Thread):
    """Polls the API and records when each event first becomes queryable.

    The window starts at the event time of the oldest published event of that kind not
    yet seen (never more than 30 s back) and ends in the future, so each poll reads only
    what may still be missing instead of a fixed 30 s of history.
    """

    def __init__(
        self, api_url: str, published: list[Any], interval_s: float = POLL_INTERVAL_S
    ) -> None:
        super().__init__(name="latency-poller", daemon=True)
        self.api_url = api_url
        self.published = published
        self.interval_s = interval_s
        self.first_seen: dict[Key, float] = {}
        # The gateway's receive time of each event seen (same machine, same clock): splits
        # publish -> queryable into MQTT + gateway, and Kafka + processors + store.
        self.received_at: dict[Key, float] = {}
        # The start of the last poll of the same kind that did not return the key yet:
        # the event became queryable after that moment (a lower bound on its latency).
        self.not_seen_at: dict[Key, float] = {}
        self.pending: dict[Key, int] = {}
        self.censored: set[Key] = set()  # left the window unseen: latency > MAX_WINDOW_MS
        self._consumed = 0
        self.polls = 0
        self.poll_seconds: list[float] = []
        self.cycle_seconds: list[float] = []  # start to start: how late a poll can see an event
        self._last_start: float | None = None
        self.window_rows: list[int] = []
        self.in_response_duplicates = 0
        self.truncated_polls = 0
        self.errors = 0
        self.last_error = ""
        self._halt = threading.Event()
        self._ready = threading.Event()

    def stop(self) -> None:
        self._halt.set()

    def _take_published(self) -> None:
        n = len(self.published)  # the fleet only appends; entries up to n are complete
        for kind, robot, ts, _wall in self.published[self._consumed : n]:
            key = (kind, robot, ts)
            if key not in self.first_seen:
                self.pending[key] = ts
        self._consumed = n

    def _get(
        self, client: httpx.Client, path: str, f: int, t: int
    ) -> tuple[list[Any], float, float]:
        asked_at = time.time()
        r = client.get(f"{self.api_url}{path}", params={"from": f, "to": t, "limit": POLL_LIMIT})
        seen_at = time.time()
        r.raise_for_status()
        return r.json(), asked_at, seen_at

    def run(self) -> None:
        self._ready.set()
        with httpx.Client(timeout=30) as client:
            while not self._halt.is_set():
                started = time.monotonic()
                self._take_published()
                now_ms = time.time_ns() // 1_000_000
                oldest_allowed = now_ms - MAX_WINDOW_MS
                for key in [k for k, ts in self.pending.items() if ts < oldest_allowed]:
                    del self.pending[key]  # left the window unseen; the final scan decides
                    self.censored.add(key)
                if self._last_start is not None:
                    self.cycle_seconds.append(started - self._last_start)
                self._last_start = started
                truncated = False
                try:
                    rows = 0
                    for kind, path in (
                        (KEYS_PER_POSE, "/api/v1/poses"),
                        (KEYS_PER_CHUNK, "/api/v1/chunk-events"),
                    ):
                        # Per kind: chunks and poses are stored by different agents, and a
                        # chunk still on its way must not widen the (larger) pose window.
                        lower = min(
                            (ts for k, ts in self.pending.items() if k[0] == kind),
                            default=now_ms - 1000,
                        )
                        f, t = max(lower, oldest_allowed), now_ms + 5000
                        body, asked_at, seen_at = self._get(client, path, f, t)
                        rows += len(body)
                        # Rows come in event-time order: when the limit cut the answer, only
                        # pending events up to the last row returned were looked for.
                        examined_to = t
                        if len(body) >= POLL_LIMIT:
                            self.truncated_polls += 1
                            truncated = True
                            examined_to = body[-1]["ts_ms"]
                        in_this: set[Key] = set()
                        for row in body:
                            key = (kind, row["robotId"], row["ts_ms"])
                            if key in in_this:
                                self.in_response_duplicates += 1
                            in_this.add(key)
                            if key not in self.first_seen:
                                self.first_seen[key] = seen_at
                                self.received_at[key] = row["receive_time_ms"] / 1000
                                self.pending.pop(key, None)
                        for key, ts in self.pending.items():
                            if key[0] == kind and ts < examined_to:
                                self.not_seen_at[key] = asked_at
                    self.polls += 1
                    self.window_rows.append(rows)
                    self.poll_seconds.append(time.monotonic() - started)
                except (httpx.HTTPError, ValueError) as exc:
                    self.errors += 1
                    self.last_error = str(exc)[:200]
                # Every ~100 ms from the start of the last poll: the gap between polls is
                # this instrument's resolution, so a slow poll is not followed by a wait as
                # long again (that stretched the cycle up to 1 s at 5,000 robots). Only a poll cut at the row limit (a backlog wider than one
                # read) backs off to half the time, so a lagging pipeline does not get a
                # read load of its own.
                took = time.monotonic() - started
                self._halt.wait(max(self.interval_s - took, took if truncated else 0.0))


_LIVE_KINDS = {"pose": KEYS_PER_POSE, "chunk": KEYS_PER_CHUNK}


class LiveListener(threading.Thread):
    """Notes when the API sent each event on its live WebSocket (`/api/v1/live`).

    The history sink pushes a batch live only after its insert returned, so an event is
    queryable by the time the API sends it (`sent_ms`, stamped by the server on the same
    clock): an upper bound on publish -> queryable as tight as the push itself, where a
    poll adds up to a poll cycle and its own duration. The server's stamp, not this
    thread's receive time, because this process also runs the load generator's 1,000
    robots and a thread here waits its turn for the GIL. It also stands for a live UI
    watching the floor, which production has anyway, and asks for batched frames as the
    UI does (`?batch=true`: a JSON array of events per message, each with its `sent_ms`).
    """

    def __init__(self, api_url: str) -> None:
        super().__init__(name="latency-live-listener", daemon=True)
        self.ws_url = "ws" + api_url.removeprefix("http") + "/api/v1/live?batch=true"
        self.pushed_at: dict[Key, float] = {}
        self.messages = 0
        self.errors = 0
        self.last_error = ""
        self.connected = threading.Event()
        self._halt = threading.Event()

    def stop(self) -> None:
        self._halt.set()

    def run(self) -> None:
        from websockets.sync.client import connect

        try:
            with connect(self.ws_url, max_size=None, open_timeout=10, close_timeout=1) as ws:
                self.connected.set()
                while not self._halt.is_set():
                    try:
                        raw = ws.recv(timeout=0.5)
                    except TimeoutError:
                        continue
                    self.note(raw)
        except Exception as exc:  # noqa: BLE001 - reported with the results, the poll still counts
            self.errors += 1
            self.last_error = str(exc)[:200]
        finally:
            self.connected.set()  # never leave a waiter hanging

    def note(self, raw: str | bytes) -> None:
        """Notes the send time of each event in one message: a batched frame (a JSON
        array) or a single event (a server from before batching)."""
        data = json.loads(raw)
        for m in data if isinstance(data, list) else [data]:
            self.messages += 1  # events, whichever way they were framed
            kind = _LIVE_KINDS.get(m.get("type"))
            if kind is not None:
                self.pushed_at.setdefault((kind, m["robotId"], m["ts_ms"]), m["sent_ms"] / 1000)


class DrainWatch:
    """When the drain after the fleet stops is over: drained once the store counts every
    expected event; given up once its counts have not grown for DRAIN_STALL_S (what is
    missing then is lost, not late) or after DRAIN_MAX_S in all."""

    def __init__(
        self, expected: dict[str, int], stall_s: float = DRAIN_STALL_S, max_s: float = DRAIN_MAX_S
    ) -> None:
        self.expected = expected
        self.stall_s, self.max_s = stall_s, max_s
        self.drained_s: float | None = None
        self._last_total = -1
        self._last_growth_s = 0.0

    def observe(self, elapsed_s: float, counts: dict[str, int]) -> None:
        if all(counts[k] >= n for k, n in self.expected.items()):
            self.drained_s = elapsed_s
        total = sum(counts[k] for k in self.expected)
        if total > self._last_total:
            self._last_total, self._last_growth_s = total, elapsed_s

    def given_up(self, elapsed_s: float) -> bool:
        if self.drained_s is not None:
            return elapsed_s - self.drained_s > self.stall_s  # the poller had its moment
        return elapsed_s >= self.max_s or elapsed_s - self._last_growth_s >= self.stall_s
