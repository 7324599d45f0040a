"""The service's page: GET / (static/index.html), its scripts GET /page.js and GET /route.js, and GET /tiles/{row},
a gallery tile's image.

The page is plain HTML and JavaScript, no build step and nothing fetched from elsewhere: page.js posts the dropped
image to /localize, route.js a route's frames and odometry to /localize/route (and plays the track on a map of the
tiles), and both draw the answer with textContent, DOM nodes and a canvas only, so nothing in an answer or a file
name is read as markup. Its Content-Security-Policy lets it load scripts and images from this service only.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI, HTTPException
from fastapi.responses import FileResponse, Response

from geoloc.apps.query import QueryError

STATIC = Path(__file__).with_name("static")
# the rest of the security headers, and the policy of every other response, come from headers.py
PAGE_HEADERS = {"Content-Security-Policy": "default-src 'none'; script-src 'self'; connect-src 'self'; "
                                          "img-src 'self' blob:; style-src 'self' 'unsafe-inline'; "
                                          "base-uri 'none'; form-action 'none'; frame-ancestors 'none'"}
IMAGE_TYPES = {".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".png": "image/png"}
SCRIPTS = ("page", "route")  # static/NAME.js, served at /NAME.js


def add_page(app: FastAPI, localizer) -> None:
    """Add the page's routes to `app`; /tiles needs `localizer.tile(row)` (a file path, or QueryError)."""

    @app.get("/", include_in_schema=False)
    async def page() -> Response:
        return Response((STATIC / "index.html").read_bytes(), media_type="text/html; charset=utf-8",
                        headers=PAGE_HEADERS)

    @app.get("/{name}.js", include_in_schema=False)
    async def script(name: str) -> Response:
        if name not in SCRIPTS:
            raise HTTPException(404, f"no script /{name[:40]}.js: the page's scripts are "
                                     f"{', '.join(f'/{n}.js' for n in SCRIPTS)}")
        return Response((STATIC / f"{name}.js").read_bytes(), media_type="text/javascript; charset=utf-8",
                        headers=PAGE_HEADERS)

    @app.get("/tiles/{row}")
    def tile(row: str) -> Response:
        """The image file of gallery row `row` (0-based, as the answer's topk[i]["row"] gives it)."""
        path = localizer.tile(row)
        kind = IMAGE_TYPES.get(Path(path).suffix.lower())
        if kind is None:
            raise QueryError("row", f"gallery row {row}'s tile {Path(path).name!r} is not a JPEG or PNG file", 415)
        return FileResponse(path, media_type=kind)
