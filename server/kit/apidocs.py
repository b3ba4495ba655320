"""The API's reference at ``/docs``: Swagger UI from the installed ``fastapi-offline`` package.

FastAPI's own page loads Swagger UI from a CDN (blank offline) and starts it with an inline
script, which the pages' Content-Security-Policy refuses. This page takes both files from the
package, starts Swagger UI from ``web/static/apidocs.js`` and keeps the CSP, widened only to let
Swagger's stylesheet draw its icons from ``data:`` images. No request leaves the server.
"""

from __future__ import annotations

from pathlib import Path

import fastapi_offline
from fastapi import FastAPI, Request
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

from server.kit.pages import CONTENT_SECURITY_POLICY, SECURITY_HEADERS, templates

DOCS_PATH = "/docs"
ASSETS_PATH = "/docs/assets"
SWAGGER_DIR = Path(fastapi_offline.__file__).parent / "static"
DOCS_HEADERS = SECURITY_HEADERS | {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY.replace(
        "img-src 'self'", "img-src 'self' data:"
    ),
}


async def api_docs(request: Request) -> HTMLResponse:
    """Swagger UI for this app's OpenAPI document. (A module function, not a closure over the
    app: FastAPI caches facts about each endpoint callable process-wide, and a closure per app
    kept every app ever made alive.)"""
    app = request.app
    root = request.scope.get("root_path", "")
    html = templates.get_template("apidocs.html").render(
        title=f"{app.title} API",
        openapi_url=f"{root}{app.openapi_url}",
        assets=f"{root}{ASSETS_PATH}",
    )
    return HTMLResponse(html, headers=DOCS_HEADERS)


def mount_api_docs(app: FastAPI) -> None:
    """Serve the Swagger UI page at /docs and its files under /docs/assets (create the app
    with `docs_url=None` so that FastAPI's CDN page does not take /docs first)."""
    if app.docs_url is not None:
        raise ValueError("create the app with docs_url=None: FastAPI's own /docs uses a CDN")
    app.mount(ASSETS_PATH, StaticFiles(directory=SWAGGER_DIR), name="apidocs-assets")
    app.add_api_route(DOCS_PATH, api_docs, methods=["GET"], include_in_schema=False)
