"""The web page at ``/`` and its files at ``/static`` (viewer and deformation tool).

The page (``service/static/index.html``, ``style.css``, ``js/``) and the sample meshes are
committed; the three.js modules it imports are built into ``service/static/vendor/`` by
``npm ci --prefix web`` (see ``web/build.mjs``). Without them ``/`` answers 503 with a page
that names that command. The page uses only the public API; none of these routes are part of
the OpenAPI document.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from starlette.responses import FileResponse, HTMLResponse, Response
from starlette.staticfiles import StaticFiles
from starlette.types import Scope

from service.http.security import page_policy

STATIC = Path(__file__).resolve().parents[2] / "static"
VENDOR_MANIFEST = STATIC / "vendor" / "three" / "manifest.json"
BUILD_COMMAND = "npm ci --prefix web"

router = APIRouter(include_in_schema=False)

_MISSING = f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Web assets not built</title>
<style>body{{font:15px/1.5 system-ui,sans-serif;max-width:42rem;margin:4rem auto;color:#1f2933}}
code{{background:#eef2f6;padding:.1rem .3rem;border-radius:3px}}</style></head>
<body><h1>The web page's assets are not built</h1>
<p>The three.js modules the page loads are installed from the npm registry and copied into
<code>service/static/vendor/</code> by running, in the repository root:</p>
<p><code>{BUILD_COMMAND}</code></p>
<p>then reload this page. The HTTP API works without them: see <a href="/docs">/docs</a>.</p>
</body></html>
"""


class StaticAssets(StaticFiles):
    """StaticFiles whose responses are revalidated (ETag) on every use, so an upgraded page
    never runs against cached modules of the previous version."""

    async def get_response(self, path: str, scope: Scope) -> Response:
        response = await super().get_response(path, scope)
        response.headers.setdefault("Cache-Control", "no-cache")
        if response.status_code == 304 and path.endswith((".html", ".htm")):
            # The 200's policy hashes the page's inline scripts: the 304 repeats it.
            response.headers["Content-Security-Policy"] = page_policy(
                (STATIC / path).read_bytes())
        return response


def assets_built() -> bool:
    """Whether ``npm ci --prefix web`` built the page's vendored modules."""
    return VENDOR_MANIFEST.is_file()


@router.api_route("/", methods=["GET", "HEAD"])
async def index() -> Response:
    if not assets_built():
        return HTMLResponse(_MISSING, status_code=503)
    return FileResponse(STATIC / "index.html", media_type="text/html",
                        headers={"Cache-Control": "no-cache"})


@router.api_route("/favicon.ico", methods=["GET", "HEAD"])
async def favicon() -> Response:
    return FileResponse(STATIC / "favicon.svg", media_type="image/svg+xml")


def static_files() -> StaticAssets:
    """The ``/static`` mount.

    Returns:
        The static files app (``app.mount("/static", static_files(), name="static")``).
    """
    return StaticAssets(directory=STATIC, check_dir=False)
