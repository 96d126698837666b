"""The browser face of the service: the dashboard at ``/`` and offline API docs.

Everything here is static files shipped in the package (``server/web/static``): one HTML
page, one vanilla script, one stylesheet, and pinned third-party bundles vendored with their
licences (``static/vendor/README.md``). No build step, no CDN: a machine cut off from the
internet gets the same dashboard, viewer, Swagger UI and ReDoc. The page talks to the API
with the same bearer tokens as any client; it holds no server-side session.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.staticfiles import StaticFiles

STATIC = Path(__file__).resolve().parent / "static"
VENDOR = "/static/vendor"


def install(app: FastAPI) -> None:
    """Serve the dashboard at ``/``, the static files at ``/static`` and the API docs at
    ``/docs`` and ``/redoc`` from the package (the app must be made with ``docs_url=None,
    redoc_url=None`` so FastAPI's CDN-loading pages do not shadow these)."""
    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.get("/", include_in_schema=False)
    def dashboard() -> FileResponse:
        # no-cache: a new version of the script must not meet an old cached page
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})

    @app.get("/docs", include_in_schema=False)
    def swagger() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url or "/openapi.json",
            title=f"{app.title} API",
            swagger_js_url=f"{VENDOR}/swagger-ui/swagger-ui-bundle.js",
            swagger_css_url=f"{VENDOR}/swagger-ui/swagger-ui.css",
            swagger_favicon_url=f"{VENDOR}/swagger-ui/favicon-32x32.png",
        )

    @app.get("/redoc", include_in_schema=False)
    def redoc() -> HTMLResponse:
        return get_redoc_html(
            openapi_url=app.openapi_url or "/openapi.json",
            title=f"{app.title} API",
            redoc_js_url=f"{VENDOR}/redoc/redoc.standalone.js",
            redoc_favicon_url=f"{VENDOR}/swagger-ui/favicon-32x32.png",
            with_google_fonts=False,
        )
