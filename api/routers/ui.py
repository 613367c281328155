"""The replay UI (replay-ui/, built by Vite into replay-ui/dist): `/`, `/controller`, assets.

The pages are not API resources, so they stay out of the OpenAPI schema. Without a build
the pages answer 503 with the command that makes one.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, Depends, HTTPException, Request
from fastapi.responses import FileResponse, HTMLResponse

from ..access import PUBLIC
from ..context import context_of

# The pages and their assets hold no data (it comes from the API, with its own scopes).
router = APIRouter(tags=["ui"], include_in_schema=False, dependencies=[Depends(PUBLIC)])
DIST = Path(__file__).resolve().parents[2] / "replay-ui" / "dist"
# Vite names every asset by its content hash, so a cached copy is never stale.
IMMUTABLE = "public, max-age=31536000, immutable"

MISSING = """<!doctype html><html><head><title>mapservice</title></head><body>
<h1>The replay UI is not built</h1>
<p>Build it with <code>make ui</code> (or <code>cd replay-ui &amp;&amp; npm ci &amp;&amp; npm run build</code>),
then reload. <code>make up</code> builds it when needed.</p>
<p>The API itself is running: <a href="/docs">/docs</a>.</p></body></html>"""


def _dist(request: Request) -> Path:
    """The build to serve: MAPSERVICE_UI_DIR (an installed image), else the checkout's."""
    return context_of(request.app).settings.ui_dir or DIST


def _page(request: Request, name: str) -> FileResponse | HTMLResponse:
    page = _dist(request) / name
    if not page.is_file():
        return HTMLResponse(MISSING, status_code=503)
    # The page names the current asset hashes, so it must be revalidated.
    return FileResponse(page, media_type="text/html", headers={"Cache-Control": "no-cache"})


@router.get("/", operation_id="getReplayUi", response_model=None)
def index(request: Request) -> FileResponse | HTMLResponse:
    return _page(request, "index.html")


@router.get("/controller", operation_id="getControllerUi", response_model=None)
def controller(request: Request) -> FileResponse | HTMLResponse:
    return _page(request, "controller.html")


@router.get("/assets/{name}", operation_id="getUiAsset")
def asset(name: str, request: Request) -> FileResponse:
    assets = _dist(request) / "assets"
    try:
        path = (assets / name).resolve()
        found = path.parent == assets.resolve() and path.is_file()
    except (ValueError, OSError):  # an embedded NUL (/assets/%00), a name too long: no file
        found = False
    if not found:
        raise HTTPException(404, f"no UI asset {name[:100]!r}; rebuild the UI if the page is stale")
    return FileResponse(path, headers={"Cache-Control": IMMUTABLE})
