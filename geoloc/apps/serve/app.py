"""The query service: one street image in, the localizer's answer (top-k references, position, heading) out.

    app = create_app(Localizer.load(ckpt, gallery))   # the model and the gallery are loaded once, by the caller
    uvicorn.run(app)                                   # or: geoloc serve ckpt=... gallery=DIR

GET / -> the page (static/index.html + page.js: drop a street image, see the answer; route.js: play a route's
track); GET /tiles/{row} -> the gallery's tile image of that row (what the page shows of the top-k)
GET /health -> {"status": "ok", **localizer.info()}
POST /localize, multipart/form-data: file field `image`; `fov` (degrees, (0, 360], default 360: a panorama),
`topk` (1 to max_topk, default 5), `heading` (degrees clockwise from north when known, or `search`; default: as
the checkpoint was trained, Localizer.default_heading), `heading_prior` (± degrees around heading to search) and
`abstain` (a confidence threshold in [0, 1]) as form fields or query parameters, each given once ->
localizer.localize(...)'s answer, as JSON.
POST /localize/route: a route's frames and odometry in one request, the answers fused into a track
(route_endpoint.py).
No response carries CORS headers: a page of another origin cannot read the answers. Every response carries a
Content-Security-Policy and frame protection (headers.py). FastAPI's /docs and /redoc, which load scripts from a
CDN, are off unless `api_docs`; /openapi.json describes the API.

The settings are read once, at the door: FastAPI fills a QueryForm (form.py, a Pydantic model) from the form
fields and one from the query parameters, and `localizer.parse(**sent)` parses them into the QuerySettings that
the rest of the request trusts.
`localizer` is anything with `parse(fov=, topk=, heading=, heading_prior=, abstain=)` (the settings as sent, text
or None: a QuerySettings, or QueryError naming the setting), `check(width, height, query, name=)` (the image's
size against the limits, before it is decoded: QueryError naming the limit), `localize(image, query, name=,
deadline=)` (image: H×W×3 uint8 RGB; returns a LocalizationResult, whose to_json() is the answer, or a
JSON-serialisable dict), `info()` (a JSON-serialisable dict) and, for /tiles, `tile(row)` (the file of gallery row
`row`, or QueryError), e.g. geoloc.apps.localize.Localizer.
Bad input gets a 4xx whose `detail` says what is wrong and what to do; a failure inside the localizer gets a 500
with its message. Neither stops the server.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from typing import Annotated

from fastapi import Depends, FastAPI, File, Form, HTTPException, Query, Request, UploadFile
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response

from geoloc.apps.query import QueryError
from geoloc.apps.serve.body_limit import BodyLimit
from geoloc.apps.serve.form import QueryForm, each_field_once, sent_settings
from geoloc.apps.serve.form import HINTS as FIELD_HINTS
from geoloc.apps.serve.headers import DOCS_POLICY, SecurityHeaders
from geoloc.apps.serve.page import add_page
from geoloc.apps.serve.route_endpoint import FILES as ROUTE_FILES
from geoloc.apps.serve.route_endpoint import MAX_FRAMES, add_route
from geoloc.apps.serve.upload import SEND, decode_upload

log = logging.getLogger("geoloc.apps.serve")

MAX_BYTES = 32 * 2**20
MAX_SECONDS = 10.0  # a query's turn at the network: past it, its heading search stops with a 503
HINTS = {"image": SEND, **ROUTE_FILES, **FIELD_HINTS}  # what each field is for, named in a 422


class Service(FastAPI):
    """FastAPI with SecurityHeaders outermost, outside Starlette's error middleware, so that its 500s get them too."""

    def __init__(self, policies: dict[str, str], **kwargs):
        self.policies = policies  # SecurityHeaders' policies by path
        super().__init__(**kwargs)

    def build_middleware_stack(self):
        return SecurityHeaders(super().build_middleware_stack(), self.policies)


def create_app(localizer, max_bytes: int = MAX_BYTES, max_seconds: float = MAX_SECONDS,
               api_docs: bool = False, route=None, max_frames: int | None = None) -> FastAPI:
    """A FastAPI app answering /health, /localize and /localize/route from `localizer` (module docstring);
    api_docs: serve FastAPI's /docs and /redoc (their scripts come from cdn.jsdelivr.net); route: the sequence
    filter's FilterConfig (None: its defaults); max_frames: the frames one route request may send (None:
    route_endpoint.MAX_FRAMES)."""
    docs = {"docs_url": "/docs", "redoc_url": "/redoc"} if api_docs else {"docs_url": None, "redoc_url": None}
    app = Service({path: DOCS_POLICY for path in docs.values() if path}, title="geoloc",
                  summary="Where was this street image taken? Retrieval against a saved gallery.", **docs)
    app.add_middleware(BodyLimit, max_bytes=max_bytes)
    app.add_exception_handler(RequestValidationError, readable_validation_error)
    app.add_exception_handler(QueryError, query_error)
    # One request at a time reaches the decoder and the network. A torch forward pass already uses every core, so
    # two at once on a small CPU only share them (no gain in throughput); one at a time keeps the memory to one
    # decoded image and one set of activations, and each result independent of what else is in flight. Waiting
    # requests hold a threadpool thread and their spooled upload, nothing more; /health does not wait. A turn lasts
    # at most max_seconds (the localizer's deadline) plus one pass of a few candidate headings.
    one_at_a_time = threading.Lock()

    @app.get("/health")
    async def health() -> dict:
        return {"status": "ok", **localizer.info()}

    add_page(app, localizer)

    # a sync endpoint: FastAPI runs it in its threadpool, so the event loop stays free while the network runs
    @app.post("/localize", dependencies=[Depends(each_field_once("/localize", {"image": SEND}))])
    def localize(image: Annotated[UploadFile, File(description="the street image: JPEG or PNG")],
                 form: Annotated[QueryForm, Form()], params: Annotated[QueryForm, Query()]) -> Response:
        sent, where = sent_settings(form, params)
        filename = image.filename or "image"
        try:
            query = localizer.parse(**sent)  # the door: parsed once, trusted below
        except QueryError as err:
            raise worded(err, where, max_seconds) from None
        with one_at_a_time:
            deadline = time.monotonic() + max_seconds
            try:
                rgb, _ = decode_upload(image.file.read(), filename, lambda width, height: localizer.check(
                    width, height, query, name=f"the upload {filename!r}"))
            except QueryError as err:
                raise worded(err, where, max_seconds) from None
            try:
                result = localizer.localize(rgb, query, name=image.filename, deadline=deadline)
                body = json.dumps(result.to_json() if hasattr(result, "to_json") else result, allow_nan=False)
            except QueryError as err:
                raise worded(err, where, max_seconds) from None
            except Exception as err:  # the server answers and stays up; the traceback goes to its log
                log.exception("localize failed for %r", image.filename)
                raise HTTPException(500, f"localization failed: {type(err).__name__}: {err}. The server is still "
                                         "up; its log holds the traceback") from None
        return Response(body, media_type="application/json")

    from geoloc.sequence.particle_filter import FilterConfig

    add_route(app, localizer, one_at_a_time, max_seconds, route or FilterConfig(), worded, max_frames or MAX_FRAMES)
    return app


def worded(err: QueryError, where: dict, max_seconds: float) -> QueryError:
    """err with where its setting came from (form field or query parameter), or the server's time limit."""
    if err.key in where:
        return QueryError(err.key, f"{where[err.key]} {err}", err.status)
    if err.key == "max_seconds":
        return QueryError(err.key, f"{err} (this server stops a query after max_seconds={max_seconds:g} s of "
                                   "work, so that the next one gets its turn)", err.status)
    return err


async def query_error(request: Request, exc: QueryError) -> JSONResponse:
    """A bad setting, an image over a limit or an unreadable image: its status, the message, and the key named."""
    return JSONResponse({"detail": str(exc), "key": exc.key}, status_code=exc.status)


async def readable_validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    """FastAPI's 422, as one sentence per bad field saying what the field is for; an empty request is a 400."""
    problems, errors = [], []
    for error in exc.errors():
        field = str(error["loc"][-1])
        where = {"body": "form field", "query": "query parameter"}.get(error["loc"][0], error["loc"][0])
        problems.append(f"{where} '{field}': {error['msg']} ({HINTS.get(field, 'unknown field')})")
        errors.append({"field": field, "in": where, "problem": error["msg"]})
    empty = request.headers.get("content-length") in (None, "0") and "transfer-encoding" not in request.headers
    status = 400 if empty and any(e["field"] == "image" for e in errors) else 422
    if status == 400:
        problems = [f"the request body is empty: {SEND}"]
    return JSONResponse({"detail": "; ".join(problems), "errors": errors}, status_code=status)
