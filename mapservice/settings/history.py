"""The history: what the gateway admits, how long it is kept, the service's clock, and how the
processors batch it into the store and snapshot it."""

from __future__ import annotations

from pydantic import BaseModel, Field


class HistorySettings(BaseModel):
    """Ingest validation, retention, the (possibly simulated) clock, batching and snapshots."""

    # Validation
    chunk_width: int = Field(100, ge=1, le=4096, description="Used until a map meta is set.")
    chunk_height: int = Field(100, ge=1, le=4096)
    max_grid: int = Field(1000, ge=1, description="Row/column bound until a map meta is set.")
    max_message_bytes: int = Field(256 * 1024, ge=1024)
    max_future_skew_s: float = Field(300.0, ge=0)
    ingest_new_robots_limit: str = Field(
        "10000/minute",
        description=(
            "Distinct robot ids the gateway has not seen before that it admits, in the `limits` "
            "notation (`;` between limits); beyond it a message of a new robot is dead-lettered "
            "`too_many_new_robots` (robots already seen pass). Bounds a flood of made-up ids "
            "where the broker does not authenticate robots. Empty: no limit."
        ),
    )
    # At most 24: receive-minus-event lag is stored in Int32 milliseconds.
    retention_days: int = Field(
        7,
        ge=1,
        le=24,
        description=(
            "History kept, in days of the service's clock; the processors' retention step drops "
            "older days and carries the floor forward."
        ),
    )
    # The service's clock (mapservice/adapters/clock.py): the wall clock by default; a
    # start instant and a rate run it simulated (tests drive weeks of history in minutes
    # through the same code production runs).
    clock_start: str = Field(
        "",
        description=(
            "Simulated clock: the instant (ISO 8601 UTC or epoch ms) the service's clock reads at "
            "MAPSERVICE_CLOCK_ORIGIN; empty: the wall clock."
        ),
    )
    clock_rate: float = Field(
        1.0,
        gt=0,
        le=1_000_000,
        description=(
            "Simulated clock: simulated seconds per real second (with MAPSERVICE_CLOCK_START)."
        ),
    )
    clock_origin: str = Field(
        "",
        description=(
            "Simulated clock: the real instant (ISO 8601 UTC or epoch ms) at which it reads "
            "MAPSERVICE_CLOCK_START; set the same on every process of a stack so their clocks "
            "agree; empty: when the process starts."
        ),
    )

    # Processors
    # Large enough that a backlog (after a slow insert) is caught up in one or two inserts:
    # each insert and its views cost a fixed ~30 ms, and 2,000 made 5,000 robots lag.
    sink_batch_size: int = Field(10000, ge=1)
    sink_batch_seconds: float = Field(
        0.2, gt=0, description="Longest wait to fill a history batch."
    )
    # A short window costs each insert's fixed cost more often; it is taken only while
    # stores are quick, i.e. while there is CPU to spare (processors/batch_window.py).
    sink_batch_min_seconds: float = Field(
        0.1,
        gt=0,
        description=(
            "Shortest wait to fill a history batch, taken while batches are stored quickly; the "
            "wait grows toward sink_batch_seconds as storing slows down."
        ),
    )
    # Each store writes a part of every table it fills, and a small day partition is
    # rewritten whole by the merge its new parts start: a quiet plant gathers about
    # batch_window.FILL_EVENTS a batch for up to this long (its events' freshness: the live
    # stream follows the store) instead of storing a handful five times a second.
    sink_quiet_batch_seconds: float = Field(
        0.5,
        gt=0,
        description=(
            "Longest wait to fill a history batch at a quiet plant's arrival rate (about 50 "
            "events a batch, while storing is quick); the live stream follows the store, so a "
            "plant of a few dozen robots sees its events up to this much later."
        ),
    )
    # Feeding the pose views costs a fixed ~30 ms per insert: paid once a second, not per
    # batch (processors/history_consumer.py).
    sink_views_seconds: float = Field(
        1.0,
        gt=0,
        description=(
            "Longest the derived pose views (downsampled replay, timeline), the conflicts and the "
            "offset commits lag behind the stored history: the views are fed and the conflicts "
            "written once per this interval (at once when idle)."
        ),
    )

    snapshot_every_s: float = Field(600.0, ge=1, description="Snapshot interval of map and robots.")
    snapshot_grace_s: float = Field(
        60.0, ge=0, description="Snapshot S is built once now > S + grace."
    )
    snapshot_tick_s: float | None = Field(
        None,
        ge=0.2,
        description=(
            "Period in real seconds of the snapshot timer (late-event repairs, snapshots, "
            "the retention step); unset: a quarter of the snapshot interval, at most 30 s "
            "of the service's clock."
        ),
    )

    @property
    def retention_ms(self) -> int:
        return self.retention_days * 86_400_000
