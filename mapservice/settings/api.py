"""The HTTP API: its address, credentials and access rules, limits, timeouts and queues."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, Field, SecretStr


class ApiSettings(BaseModel):
    """The API's address, the UI it serves, who may do what, and how much it takes at once."""

    api_host: str = "127.0.0.1"
    api_port: int = 8080
    ui_dir: Path | None = Field(
        None, description="Built replay UI to serve; empty: replay-ui/dist of the checkout."
    )
    admin_token: SecretStr = Field(
        SecretStr(""),
        description=(
            "Administrator credential (Authorization: Bearer ...): deletes, changing the map's "
            "geometry, everything else. Empty: generated on first start in local mode "
            "(DATA_DIR/secrets/admin-token); required (>= 32 characters) in production mode."
        ),
    )
    api_read_access: Literal["open", "token"] = Field(
        "open",
        description=(
            "`open`: reads need no credential (2019 robots read anonymously); `token`: every "
            "read needs a reader, writer, robot, operator or admin token."
        ),
    )
    api_reader_tokens: SecretStr = Field(
        SecretStr(""),
        description=(
            "Viewer credentials, comma-separated: read only. Empty: generated in local mode when "
            "api_read_access is `token` (DATA_DIR/secrets/reader-token)."
        ),
    )
    api_writer_tokens: SecretStr = Field(
        SecretStr(""),
        description=(
            "Robot/writer credentials, comma-separated (one per robot or integration): the 2019 "
            "REST writes (POST/PUT meta, POST chunks) and every read. Empty: generated in local "
            "mode (DATA_DIR/secrets/writer-token); in production, no REST writes but the admin's."
        ),
    )
    api_operator_tokens: SecretStr = Field(
        SecretStr(""),
        description=(
            "Operator credentials, comma-separated: every read, editing the annotations "
            "(points of interest, zones) and commanding robots. Empty: generated in local mode "
            "(DATA_DIR/secrets/operator-token)."
        ),
    )
    api_robot_tokens: SecretStr = Field(
        SecretStr(""),
        description=(
            "Robots' own REST credentials, `robotId=token` pairs, comma-separated: a writer "
            "token bound to one robot, which may POST chunks only under its own robotId (403 "
            "otherwise), as its MQTT user may publish only on its own topics."
        ),
    )
    api_metrics_access: Literal["open", "token", "off"] | None = Field(
        None,
        description=(
            "/metrics: `open`, `token` (the metrics or the admin token) or `off` (404). Empty: "
            "open in local mode, token in production mode."
        ),
    )
    api_metrics_token: SecretStr = Field(
        SecretStr(""),
        description=(
            "The scraper's credential for /metrics (Prometheus `authorization`); it opens nothing else."
        ),
    )
    api_docs_access: Literal["open", "token", "off"] | None = Field(
        None,
        description=(
            "/docs, /redoc and /openapi.json: `open`, `token` (a reader, writer or admin token) or "
            "`off` (404). "
            "Empty: open in local mode, token in production mode."
        ),
    )
    api_rate_limit: str = Field(
        "200/second;6000/minute",
        description=(
            "Requests per credential (or per client address when anonymous) in the `limits` "
            "notation, several separated by `;`; over it 429 with Retry-After. Empty: no limit. "
            "Probes (/healthz, /readyz) are not counted."
        ),
    )
    api_max_live_clients: int = Field(
        500,
        ge=0,
        description=(
            "WebSocket clients of /api/v1/live per API process; one more is closed with 1013 "
            "(try again later) and a reason naming this setting."
        ),
    )
    api_live_compression: bool = Field(
        False,
        description=(
            "Offer permessage-deflate on /api/v1/live. Off: compressing each message cost the "
            "API ~5 µs of CPU per event and viewer at 6,000 events/s (BENCHMARKS.md); a live "
            "message is ~300 bytes."
        ),
    )
    api_header_timeout_s: float = Field(
        10.0,
        gt=0,
        description=(
            "A connection must send a request's line and headers within this long (from "
            "connecting, or from the previous response), else it is closed (slowloris)."
        ),
    )
    api_idle_timeout_s: int = Field(
        5,
        ge=1,
        description=(
            "An idle keep-alive connection is closed after this long (uvicorn timeout_keep_alive)."
        ),
    )
    api_body_timeout_s: float = Field(
        30.0,
        gt=0,
        description=(
            "A request body must arrive within this long once its headers did (408 otherwise)."
        ),
    )
    api_max_body_bytes: int = Field(
        1024 * 1024,
        ge=1024,
        description=(
            "Largest request body the API reads (413 beyond); /clickhouse has its own limits."
        ),
    )
    api_allowed_origins: list[str] = Field(
        default_factory=list,
        description=(
            "Origins (https://host:port) besides the API's own host whose pages may open "
            "/api/v1/live; e.g. a dashboard served elsewhere."
        ),
    )
    api_allowed_hosts: list[str] = Field(
        default_factory=list,
        description=(
            "Host names (the Host header, without port) besides 127.0.0.1, localhost, ::1, the "
            "host of public_base_url and of api_allowed_origins under which the API answers "
            "(a page of another site whose name resolves to this address: DNS rebinding); an "
            "IP address as Host and the probes are always answered, other names get a 421."
        ),
    )
    processors_status_url: str = Field(
        "",
        description=(
            "An API running apart from the processors: their health endpoint "
            "(http://host:port), whose /history-status gives /readyz's history_store and "
            "/api/v1/status (the replay UI's banner); empty: the API does not report whether "
            "the history is stored (`mapservice up` sets it)."
        ),
    )
    api_read_workers: int = Field(
        2,
        ge=1,
        description=(
            "Reads (/api/...) served at once per API process; more wait in a queue. Few: embedded "
            "ClickHouse runs one read at a time anyway, and each read's Python work competes "
            "with the processors for the interpreter (BENCHMARKS.md, the hostile-read test)."
        ),
    )
    api_read_queue: int = Field(
        32,
        ge=0,
        description=(
            "Reads waiting for one of api_read_workers; one more is 503 with Retry-After."
        ),
    )
    api_export_workers: int = Field(
        1,
        ge=1,
        description=(
            "Exports (/api/v1/exports/...) produced at once per API process, each in a thread "
            "of the exports' own pool; more wait in a queue."
        ),
    )
    api_export_queue: int = Field(
        4,
        ge=0,
        description=(
            "Exports waiting for one of api_export_workers; one more is 503 with Retry-After."
        ),
    )
    api_queue_wait_s: float = Field(
        10.0,
        gt=0,
        description=(
            "Longest a request waits in a queue (reads, exports) before it is answered "
            "503 with Retry-After."
        ),
    )
    api_caller_concurrency: int = Field(
        8,
        ge=1,
        description=(
            "Reads (or exports) one credential (or one client address when anonymous) may have "
            "running at once; more wait their turn in the pool's queue, where callers, and each "
            "caller's sessions (its pages' tabs), are served in turns."
        ),
    )
    api_caller_queue: int = Field(
        24,
        ge=1,
        description=(
            "Reads (or exports) one credential (or one client address when anonymous) may have "
            "waiting in a pool's queue; one more is 429 with Retry-After (a session of that "
            "caller with fewer waiting takes the place of the newest of the one with most)."
        ),
    )
    api_export_deadline_s: float = Field(
        300.0,
        gt=0,
        description=(
            "An export must be sent whole within this long; then it is aborted (the connection "
            "closed): a client that stops reading holds a worker and a buffer at most this long."
        ),
    )
    api_live_clients_per_caller: int = Field(
        20,
        ge=1,
        description=(
            "/api/v1/live connections per credential (or client address when anonymous); one "
            "more is refused with 429."
        ),
    )
    api_live_send_timeout_s: float = Field(
        10.0,
        gt=0,
        description=(
            "A live client whose connection takes no message for this long (it does not read) is "
            "closed with 1008 and a reason."
        ),
    )
