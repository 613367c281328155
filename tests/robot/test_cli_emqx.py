"""`mapservice robot add|list|remove --emqx` against an HTTP server answering as EMQX 5's
user API does (the fake of the registry contract suite, served on a real socket)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import httpx
import pytest

from tests.mapservice.adapters.test_robot_registry_contract import KEY, SECRET, FakeEmqx


@pytest.fixture
def emqx():
    fake = FakeEmqx()

    class Handler(BaseHTTPRequestHandler):
        def _any(self) -> None:
            body = self.rfile.read(int(self.headers.get("Content-Length") or 0))
            resp = fake.handle(
                httpx.Request(
                    self.command,
                    f"http://emqx{self.path}",
                    headers=dict(self.headers),
                    content=body,
                )
            )
            self.send_response(resp.status_code)
            self.send_header("Content-Length", str(len(resp.content)))
            self.end_headers()
            self.wfile.write(resp.content)

        do_GET = do_POST = do_PUT = do_DELETE = _any

        def log_message(self, *args) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield fake, f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()


def robot_cli(url: str, tmp_path, *args: str, secret: str = SECRET) -> subprocess.CompletedProcess:
    env = {
        **os.environ,
        "MAPSERVICE_EMQX_API_URL": url,
        "MAPSERVICE_EMQX_API_KEY": KEY,
        "MAPSERVICE_EMQX_API_SECRET": secret,
        "MAPSERVICE_DATA_DIR": str(tmp_path),
    }
    return subprocess.run(
        [sys.executable, "-m", "mapservice.cli", "robot", *args, "--emqx"],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_robot_add_list_remove_manage_emqx_users(emqx, tmp_path) -> None:
    """add stores the printed password in EMQX, list shows the robot, remove deletes it, and no Mosquitto file is written."""
    fake, url = emqx
    added = robot_cli(url, tmp_path, "add", "agv-9", "--json")
    assert added.returncode == 0, added.stderr
    cred = json.loads(added.stdout)
    assert fake.users == {"agv-9": cred["password"]} and "EMQX" in cred["storedIn"]
    assert robot_cli(url, tmp_path, "list").stdout.split() == ["agv-9"]
    again = robot_cli(url, tmp_path, "add", "agv-9")
    assert again.returncode != 0 and "--rotate" in again.stderr
    removed = robot_cli(url, tmp_path, "remove", "agv-9")
    assert removed.returncode == 0 and fake.users == {}
    assert not (tmp_path / "mqtt").exists()


def test_a_wrong_emqx_key_is_a_clear_error(emqx, tmp_path) -> None:
    """A rejected API key exits non-zero naming the settings to check, without a traceback."""
    _fake, url = emqx
    done = robot_cli(url, tmp_path, "add", "agv-9", secret="wrong")
    assert done.returncode != 0 and "MAPSERVICE_EMQX_API_KEY" in done.stderr
    assert "Traceback" not in done.stderr
