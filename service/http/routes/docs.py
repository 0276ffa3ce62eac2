"""The API documentation pages: Swagger UI at ``/docs`` and ReDoc at ``/redoc``, both reading
``/openapi.json`` and loading their scripts and styles from this service.

Their files are built into ``service/static/vendor/swagger-ui/`` and ``vendor/redoc/`` from
``web/package-lock.json`` by ``npm ci --prefix web`` (``web/build.mjs``), like the web page's
three.js, so the pages work without a network (nothing comes from a CDN). Without them a page
answers 503 naming that command; ``/openapi.json`` is served either way.
"""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from starlette.responses import HTMLResponse, Response

from service.http.routes.web import BUILD_COMMAND, STATIC

router = APIRouter(include_in_schema=False)

VENDOR = "/static/vendor"
TITLE = "Fundamental forms service"
OPENAPI_URL = "/openapi.json"


def _missing(viewer: str, directory: str) -> HTMLResponse:
    return HTMLResponse(
        "<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\">"
        f"<title>{viewer} not built</title></head><body><h1>{viewer} is not built</h1>"
        f"<p>Its files are copied into <code>service/static/vendor/{directory}/</code> by "
        f"running <code>{BUILD_COMMAND}</code> in the repository root. The OpenAPI document "
        f"is at <a href=\"{OPENAPI_URL}\">{OPENAPI_URL}</a>.</p></body></html>",
        status_code=503)


def built(directory: str) -> bool:
    """Whether ``npm ci --prefix web`` copied a viewer's files.

    Args:
        directory: Its folder under ``vendor/`` (``swagger-ui``, ``redoc``).

    Returns:
        True when its manifest is there.
    """
    return (STATIC / "vendor" / directory / "manifest.json").is_file()


@router.api_route("/docs", methods=["GET", "HEAD"])
async def swagger_ui() -> Response:
    if not built("swagger-ui"):
        return _missing("Swagger UI", "swagger-ui")
    return get_swagger_ui_html(
        openapi_url=OPENAPI_URL, title=f"{TITLE} - Swagger UI",
        swagger_js_url=f"{VENDOR}/swagger-ui/swagger-ui-bundle.js",
        swagger_css_url=f"{VENDOR}/swagger-ui/swagger-ui.css",
        swagger_favicon_url="/favicon.ico",
        # validatorUrl: no badge fetched from the public validator.
        swagger_ui_parameters={"validatorUrl": None, "tryItOutEnabled": False})


@router.api_route("/redoc", methods=["GET", "HEAD"])
async def redoc() -> Response:
    if not built("redoc"):
        return _missing("ReDoc", "redoc")
    return get_redoc_html(openapi_url=OPENAPI_URL, title=f"{TITLE} - ReDoc",
                          redoc_js_url=f"{VENDOR}/redoc/redoc.standalone.js",
                          redoc_favicon_url="/favicon.ico", with_google_fonts=False)
