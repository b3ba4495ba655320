"""GET /downloads/FILE: the SDK and slim CLI wheels, the policy template and the service's
source (server/downloads/artifacts.py)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import Response

from server.downloads.artifacts import served_download
from server.kit.errors import NotFound

router = APIRouter(include_in_schema=False)


@router.get("/downloads/{filename}")
def download(filename: str) -> Response:
    """One download, built from the sources this service runs."""
    found = served_download(filename)
    if found is None:
        raise NotFound(
            f"no download {filename!r}: a challenge's getting-started page names those there are"
        )
    return Response(
        found.content,
        media_type=found.media_type,
        headers={"Content-Disposition": f'attachment; filename="{found.filename}"'},
    )
