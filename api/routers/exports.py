"""Exports of a time window: the analysts' views as CSV or Parquet, and the map and robots
as an MCAP file that Foxglove or Lichtblick replays."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, HTTPException, Query
from fastapi.responses import Response, StreamingResponse
from pydantic import Field

from mapservice.adapters.mcap_export import ReplaySources, export_mcap
from mapservice.adapters.table_export import TABLE_FORMATS, TABLES, export_table

from ..access import READ
from ..deps import ExportPoolDep, ExportsDep, RolesDep, TimeWindow
from ..streaming import BoundedPipe, produce


async def replay_sources(roles: RolesDep) -> ReplaySources:
    """The roles a replay export reads, and no other."""
    return ReplaySources.of(roles)


ReplaySourcesDep = Annotated[ReplaySources, Depends(replay_sources)]

router = APIRouter(prefix="/api/v1/exports", tags=["exports"], dependencies=[Depends(READ)])
MAX_TABLE_SPAN_MS = 7 * 86_400_000
MAX_MCAP_SPAN_MS = 86_400_000
Dataset = Literal[
    "robot-poses",
    "chunk-changes",
    "chunk-conflicts",
    "dead-letters",
    "vehicle-states",
    "vehicle-errors",
    "vehicle-connections",
    "annotation-edits",
    "commands",
]


class TableWindow(TimeWindow):
    to: str = Field(description="End (exclusive), ISO 8601 or epoch ms; at most 7 days after from")


class McapWindow(TimeWindow):
    to: str = Field(description="End (exclusive); at most 24 hours after from")


def utc_file_time(ms: int) -> str:
    """An instant as a file name may hold it, readable: 2026-11-28_10-00-00 (UTC), with
    .250 when not on a whole second; no colons, which some file systems refuse."""
    text = datetime.fromtimestamp(ms // 1000, UTC).strftime("%Y-%m-%d_%H-%M-%S")
    return f"{text}.{ms % 1000:03d}" if ms % 1000 else text


def _filename(stem: str, from_ms: int, to_ms: int, ext: str) -> dict[str, str]:
    name = f"{stem}_{utc_file_time(from_ms)}_to_{utc_file_time(to_ms)}_UTC.{ext}"
    return {"Content-Disposition": f'attachment; filename="{name}"'}


@router.get(
    "/tables/{dataset}",
    operation_id="exportTable",
    response_class=Response,
    responses={200: {"content": {"text/csv": {}, "application/vnd.apache.parquet": {}}}},
)
async def export_table_route(
    pool: ExportPoolDep,
    store: ExportsDep,
    dataset: Dataset,
    window: Annotated[TableWindow, Query()],
    format: Literal["csv", "parquet"] = Query("csv", description="csv (with a header) or parquet"),
    robot_id: str | None = Query(
        None,
        alias="robotId",
        max_length=64,
        description="Only this robot (not for dead-letters or annotation-edits)",
    ),
) -> Response:
    """Rows of an analysts' view (docs/analysts.md) in the window, as ClickHouse writes them.
    CSV is streamed slice by slice of the window as the client reads it."""
    f, t = window.parse(MAX_TABLE_SPAN_MS)
    if store is None:
        raise HTTPException(501, "table exports need the ClickHouse store")

    def producer(out) -> None:
        if format == "parquet":  # one file: Parquet cannot be cut into slices and joined
            out.write(export_table(store, dataset, format, f, t, robot_id))
        else:
            write_csv_slices(store, dataset, f, t, robot_id, out)

    return await _stream(
        pool, producer, TABLE_FORMATS[format][1], _filename(TABLES[dataset][0], f, t, format)
    )


def write_csv_slices(
    store,
    dataset: str,
    from_ms: int,
    to_ms: int,
    robot_id: str | None,
    out,
    target_bytes: int = 4 * 1024 * 1024,
) -> None:
    """The window's CSV as consecutive time slices (each in time order, so the whole is
    too), the header once; a slice's length adapts so one holds about `target_bytes`."""
    step, cursor, header = 3_600_000, from_ms, True
    while cursor < to_ms:
        end = min(to_ms, cursor + step)
        body = export_table(store, dataset, "csv", cursor, end, robot_id)
        if not header:  # CSVWithNames: the column names are the first line
            body = body.split(b"\n", 1)[1] if b"\n" in body else b""
        if body:
            out.write(body)
            header = False
        cursor = end
        if len(body) > target_bytes:
            step = max(60_000, step // 2)
        elif len(body) < target_bytes // 8:
            step = min(6 * 3_600_000, step * 2)
    if header:  # nothing at all: still the header, as one query over the window writes it
        out.write(export_table(store, dataset, "csv", from_ms, from_ms, robot_id))


@router.get(
    "/replay.mcap",
    operation_id="exportReplayMcap",
    response_class=Response,
    responses={200: {"content": {"application/x-mcap": {}}}},
)
async def export_replay_mcap(
    pool: ExportPoolDep,
    sources: ReplaySourcesDep,
    window: Annotated[McapWindow, Query()],
) -> Response:
    """The map (`/map`, foxglove.Grid) and every robot in the window, as MCAP for Foxglove
    or Lichtblick: its pose (`/robots/<id>/pose`, foxglove.PoseInFrame), battery in %,
    charging and loaded (`/robots/<id>/state`, JSON with its JSON schema) and planned path
    (`/robots/<id>/planned_path`, foxglove.PosesInFrame, when it changes); the operators'
    annotations standing at the start and after each edit (`/annotations`,
    foxglove.SceneUpdate) and their commands with the robots' answers (`/commands`, JSON);
    streamed as it is written."""
    f, t = window.parse(MAX_MCAP_SPAN_MS)
    try:
        return await _stream(
            pool,
            lambda out: export_mcap(sources, f, t, out),
            "application/x-mcap",
            _filename("replay", f, t, "mcap"),
        )
    except ValueError as exc:
        raise HTTPException(409, str(exc)) from exc


async def _stream(pool: ThreadPoolExecutor, producer, media_type: str, headers: dict) -> Response:
    """The producer run in the exports' pool, its bytes sent as the client reads them
    (api/streaming.py); the whole within MAPSERVICE_API_EXPORT_DEADLINE_S (api/admission.py)."""
    pipe, first = await produce(pool, producer)
    return _PipeResponse(pipe, first, media_type=media_type, headers=headers)


class _PipeResponse(StreamingResponse):
    """Streams a pipe; however the response ends (sent, client gone, cancelled at the
    deadline), the pipe is aborted so its producer stops and frees its worker."""

    def __init__(self, pipe: BoundedPipe, first: bytes | None, **options) -> None:
        super().__init__(pipe.chunks(first), **options)
        self.pipe = pipe

    async def __call__(self, scope, receive, send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self.pipe.abort()
