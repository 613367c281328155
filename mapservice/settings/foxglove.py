"""The Foxglove WebSocket server: where it listens, how many clients it takes, how it treats a
slow one, how often it sends the floor (docs/foxglove.md)."""

from __future__ import annotations

from pydantic import BaseModel, Field


class FoxgloveSettings(BaseModel):
    """The Foxglove server in each API process (its access: the API's read access, Host and
    Origin rules)."""

    foxglove_enabled: bool = Field(
        True, description="Serve Foxglove and Lichtblick clients (live and replay)."
    )
    foxglove_host: str = Field(
        "127.0.0.1",
        description="Address the Foxglove WebSocket server binds (0.0.0.0: every interface).",
    )
    foxglove_port: int = Field(
        8765, ge=0, le=65535, description="Its port (Foxglove's usual 8765; 0: a free one)."
    )
    foxglove_max_clients: int = Field(
        20,
        ge=1,
        description=(
            "Foxglove clients at once per API process, live and replay together; one more is "
            "answered 503 with a reason naming this setting. A replay client costs a server of "
            "its own and reads of the history."
        ),
    )
    foxglove_max_subscriptions: int = Field(
        2000,
        ge=1,
        description=(
            "Channels one client may subscribe to at once (a robot has four); a client that "
            "subscribes to more is closed with 1008 and a reason naming this setting."
        ),
    )
    foxglove_backlog: int = Field(
        1024,
        ge=16,
        description=(
            "Messages queued per client by the SDK; when full the oldest data message is "
            "dropped (a client that falls behind loses old poses, not the floor's next version)."
        ),
    )
    foxglove_send_timeout_s: float = Field(
        10.0,
        gt=0,
        description=(
            "A client whose connection takes no bytes for this long (it does not read) is "
            "disconnected."
        ),
    )
    foxglove_client_buffer_mb: float = Field(
        16.0,
        gt=0,
        description=(
            "What the gate holds for one client that has not taken it yet, in MB (binary "
            "megabytes); a client further behind (it reads slower than its subscriptions "
            "send: the floor's grid is megabytes a second on a busy floor) is disconnected. "
            "The gate reads the SDK's side at once, so the SDK's own queue, counted in "
            "messages, not bytes, stays empty."
        ),
    )
    foxglove_max_speed: float = Field(
        3600.0,
        gt=0,
        description=(
            "Replay: the fastest playback, in history seconds a second; a client asking for "
            "more plays at this (its playback state says so). Each playback step reads what "
            "its speed covers, so this bounds a step's read of the store."
        ),
    )
    foxglove_grid_every_s: float = Field(
        1.0,
        gt=0,
        description=(
            "Live: the floor (a foxglove.Grid of the whole map) is sent at most this often "
            "while chunks change; each write is on /map/changes at once."
        ),
    )
    foxglove_annotations_every_s: float = Field(
        5.0,
        gt=0,
        description=(
            "Live: how often the standing zones and points of interest, and the conflicts "
            "and VDA 5050 errors and connection states stored since, are re-read."
        ),
    )
