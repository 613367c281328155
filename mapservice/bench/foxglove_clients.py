"""`mapservice bench foxglove`'s clients: Foxglove's own npm client (@foxglove/ws-protocol,
the one the integration test uses) in one node process (tests/foxglove_client/bench.mjs),
driven by JSON lines on its stdin (mapservice/local/node_script.py)."""

from __future__ import annotations

from pathlib import Path

from mapservice.local.checkout import FOXGLOVE_CLIENT_DIR
from mapservice.local.node_script import Event, NodeMissing, NodeScript


class NodeClients(NodeScript):
    """`node bench.mjs MODE URL ARGS...`, its stderr appended to `log_path`."""

    def __init__(self, mode: str, url: str, *args: str, log_path: Path) -> None:
        log_path.parent.mkdir(parents=True, exist_ok=True)
        try:
            super().__init__(
                FOXGLOVE_CLIENT_DIR, "bench.mjs", mode, url, *args, stderr=open(log_path, "ab")
            )
        except NodeMissing as exc:
            raise SystemExit(f"bench foxglove: {exc}") from None

    @property
    def pid(self) -> int:
        return self.proc.pid

    def closed(self) -> list[Event]:
        """The clients' connections that closed (refused or dropped by the server)."""
        with self._changed:
            return [e for e in self.events if e["event"] == "closed"]

    def server_errors(self) -> list[str]:
        """The error statuses the server sent the clients (a refused subscription...)."""
        with self._changed:
            return [str(e["message"]) for e in self.events if e["event"] == "status"]
