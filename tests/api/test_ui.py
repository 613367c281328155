"""The replay UI pages: served from replay-ui/dist, a clear message when it is not built;
the test hook only in the test build (replay-ui/dist-test)."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from mapservice.api.app import create_app
from mapservice.api.routers import ui
from mapservice.local.checkout import TEST_UI_DIR
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore


@pytest.fixture
def client() -> TestClient:
    return TestClient(create_app(Settings(), MemoryStore()))


@pytest.fixture
def dist(tmp_path, monkeypatch):
    (tmp_path / "assets").mkdir()
    (tmp_path / "index.html").write_text("<title>replay</title>")
    (tmp_path / "controller.html").write_text("<title>controller</title>")
    (tmp_path / "assets" / "main-abc123.js").write_text("console.log(1)")
    (tmp_path / "secret.txt").write_text("no")
    monkeypatch.setattr(ui, "DIST", tmp_path)
    return tmp_path


def test_root_and_controller_serve_the_built_pages(client, dist) -> None:
    """`/` is the replay page and `/controller` the game page, both revalidated on load."""
    r = client.get("/")
    assert r.status_code == 200 and "replay" in r.text
    assert r.headers["cache-control"] == "no-cache"
    assert "controller" in client.get("/controller").text


def test_assets_are_immutable_and_confined_to_the_assets_folder(client, dist) -> None:
    """Hashed assets are cached forever; nothing outside dist/assets is reachable."""
    r = client.get("/assets/main-abc123.js")
    assert r.status_code == 200 and r.headers["cache-control"].endswith("immutable")
    assert client.get("/assets/..%2Fsecret.txt").status_code == 404
    assert client.get("/assets/nope.js").status_code == 404


def test_missing_build_says_how_to_build(client, tmp_path, monkeypatch) -> None:
    """Without a build, `/` answers 503 naming the build command instead of a blank page."""
    monkeypatch.setattr(ui, "DIST", tmp_path / "absent")
    r = client.get("/")
    assert r.status_code == 503 and "npm run build" in r.text and "make ui" in r.text


def test_pages_are_not_in_the_openapi_schema(client) -> None:
    """The UI routes are pages, not API operations."""
    paths = client.get("/openapi.json").json()["paths"]
    assert "/" not in paths and "/controller" not in paths


def test_ui_dir_setting_serves_an_installed_build(tmp_path) -> None:
    """MAPSERVICE_UI_DIR points the pages and assets at a build outside the checkout."""
    (tmp_path / "assets").mkdir()
    (tmp_path / "index.html").write_text("<title>installed replay</title>")
    (tmp_path / "assets" / "app-1.js").write_text("1")
    client = TestClient(create_app(Settings(ui_dir=tmp_path), MemoryStore()))
    assert "installed replay" in client.get("/").text
    assert client.get("/assets/app-1.js").status_code == 200


def _scripts(build) -> str:
    if not (build / "index.html").is_file():
        pytest.fail(f"{build} is not built: run `make ui` first")
    return "".join(p.read_text() for p in sorted((build / "assets").glob("*.js")))


def test_the_test_hook_is_only_in_the_test_build(client) -> None:
    """The page `/` serves by default (replay-ui/dist, what `make up` and the image serve) holds
    no trace of window.__replay (src/lib/testhook.ts); the test build the browser tests and
    `mapservice bench ui` serve holds it."""
    assert client.get("/").text == (ui.DIST / "index.html").read_text()
    production, test_build = _scripts(ui.DIST), _scripts(TEST_UI_DIR)
    for trace in ("__replay", "resetFrameStats", "setCompaction"):
        assert trace not in production, f"{trace!r} is in the production build"
        assert trace in test_build, f"{trace!r} is missing from the test build"
