"""The query service: one street image in, the localizer's answer (top-k references, position, heading) out.

    app = create_app(Localizer.load(ckpt, gallery))   # the model and the gallery are loaded once, by the caller
    uvicorn.run(app)                                   # or: geoloc serve ckpt=... gallery=DIR

GET /health -> {"status": "ok", **localizer.info()}
POST /localize, multipart/form-data: file field `image`; `fov` (degrees, (0, 360], default 360: a panorama),
`topk` (>= 1, default 5) and `heading` (degrees clockwise from north when known; default: searched) as form fields
or query parameters -> localizer.localize(...)'s answer, as JSON.

`localizer` is anything with `localize(image, fov=, topk=, name=)` (image: H×W×3 uint8 RGB; returns a
LocalizationResult, whose to_json() is the answer, or a JSON-serialisable dict; it gets `heading=` only when the
request gives one) and `info()` (a JSON-serialisable dict), e.g. geoloc.apps.localize.Localizer.
Bad input gets a 4xx whose `detail` says what is wrong and what to do; a failure inside the localizer gets a 500
with its message. Neither stops the server.
"""

from __future__ import annotations

import json
import logging
import threading
from typing import Annotated

from fastapi import FastAPI, File, Form, HTTPException, Query, Request, UploadFile
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response

from geoloc.apps.serve.body_limit import BodyLimit
from geoloc.apps.serve.upload import SEND, UploadError, decode_upload

log = logging.getLogger("geoloc.apps.serve")

MAX_PIXELS = 25_000_000  # a 7,072 x 3,536 panorama; VIGOR's are 2,048 x 1,024
MAX_BYTES = 32 * 2**20
FOV_RANGE = "the horizontal field of view in degrees, in (0, 360]: 360 for a full panorama (the default)"
TOPK_RANGE = "how many references to return, an integer >= 1 (default 5)"
HEADING = ("the image's bearing in degrees clockwise from north, when known (0 for a north-aligned panorama); "
           "leave it out to have it searched")
HINTS = {"image": SEND, "fov": FOV_RANGE, "topk": TOPK_RANGE, "heading": HEADING}


def create_app(localizer, max_pixels: int = MAX_PIXELS, max_bytes: int = MAX_BYTES) -> FastAPI:
    """A FastAPI app answering /health and /localize from `localizer` (module docstring)."""
    app = FastAPI(title="geoloc", summary="Where was this street image taken? Retrieval against a saved gallery.")
    app.add_middleware(BodyLimit, max_bytes=max_bytes)
    app.add_exception_handler(RequestValidationError, readable_validation_error)
    # One request at a time reaches the decoder and the network. A torch forward pass already uses every core, so
    # two at once on a small CPU only share them (no gain in throughput); one at a time keeps the memory to one
    # decoded image and one set of activations, and each result independent of what else is in flight. Waiting
    # requests hold a threadpool thread and their spooled upload, nothing more; /health does not wait.
    one_at_a_time = threading.Lock()

    @app.get("/health")
    async def health() -> dict:
        return {"status": "ok", **localizer.info()}

    # a sync endpoint: FastAPI runs it in its threadpool, so the event loop stays free while the network runs
    @app.post("/localize")
    def localize(image: Annotated[UploadFile, File(description="the street image: JPEG or PNG")],
                 fov: Annotated[float | None, Form(gt=0, le=360, description=FOV_RANGE)] = None,
                 topk: Annotated[int | None, Form(ge=1, description=TOPK_RANGE)] = None,
                 heading: Annotated[float | None, Form(allow_inf_nan=False, description=HEADING)] = None,
                 fov_query: Annotated[float | None, Query(alias="fov", gt=0, le=360, description=FOV_RANGE)] = None,
                 topk_query: Annotated[int | None, Query(alias="topk", ge=1, description=TOPK_RANGE)] = None,
                 heading_query: Annotated[float | None, Query(alias="heading", allow_inf_nan=False,
                                                              description=HEADING)] = None) -> Response:
        fov = one_of("fov", fov, fov_query, 360.0)
        topk = one_of("topk", topk, topk_query, 5)
        heading = one_of("heading", heading, heading_query, None)
        known = {} if heading is None else {"heading": heading}
        with one_at_a_time:
            try:
                rgb = decode_upload(image.file.read(), image.filename or "image", max_pixels)
            except UploadError as err:
                raise HTTPException(err.status, str(err)) from None
            try:
                result = localizer.localize(rgb, fov=fov, topk=topk, name=image.filename, **known)
                body = json.dumps(result.to_json() if hasattr(result, "to_json") else result, allow_nan=False)
            except Exception as err:  # the server answers and stays up; the traceback goes to its log
                log.exception("localize failed for %r", image.filename)
                raise HTTPException(500, f"localization failed: {type(err).__name__}: {err}. The server is still "
                                         "up; its log holds the traceback") from None
        return Response(body, media_type="application/json")

    return app


def one_of(name: str, form_value, query_value, default):
    given = [value for value in (form_value, query_value) if value is not None]
    if len(given) == 2:
        raise HTTPException(422, f"{name} is given both as a form field and as a query parameter: give it once")
    return given[0] if given else default


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
