"""POST /localize/route: a route's frames and their odometry in one request, each frame answered as /localize
answers one image, the answers fused into a track by the sequence filter (docs/sequence.md).

Multipart form: file fields `frames` (one per frame, in route order, repeated) and `odometry` (an odometry.csv:
`frame,distance_m,heading_change_deg`, one row per frame), and /localize's settings (fov, topk, heading, ...) as
form fields or query parameters, each once. -> {"frames": [{"frame": file name, the filtered estimate
(route.RoutePlane.estimate_json: position, heading_deg, covariance_m2, tracked_mass, region_95_*), "frame_answer":
the frame's own answer}], "answers": each frame's /localize answer, "tiles": the gallery tiles the answers name, for
a page to draw (named_tiles: each distinct top-k row once, {"row", its centre in the gallery's keys, "extent_m":
[height, width] metres or null})}.

The bounds are /localize's, for the request as a whole: its body within max_bytes, one turn at the network lasting
at most max_seconds for all its frames (past it, 503 naming the frame reached), and at most max_frames frames. A
frame or an odometry file that cannot be read is a 4xx naming it; nothing is answered until every frame's header
and the odometry have been checked.
"""

from __future__ import annotations

import json
import time
from typing import Annotated

from fastapi import Depends, File, Form, HTTPException, Query, UploadFile
from fastapi.responses import Response

from geoloc.apps.query import QueryError, image_size
from geoloc.apps.serve.form import QueryForm, each_field_once, sent_settings
from geoloc.apps.serve.upload import decode_upload

MAX_FRAMES = 64  # frames a request may send: at about 0.2 s a frame on a CPU, a route within max_seconds' reach
FRAMES = "the route's frames, in route order: one file field `frames` per frame (JPEG or PNG)"
ODOMETRY = "the route's odometry.csv: frame,distance_m,heading_change_deg, one row per frame (docs/sequence.md)"
FILES = {"frames": FRAMES, "odometry": ODOMETRY}


def add_route(app, localizer, one_at_a_time, max_seconds: float, route_config, worded,
              max_frames: int = MAX_FRAMES) -> None:
    """POST /localize/route on `app`, answering from `localizer` (with `places`) through the filter of
    `route_config` (a FilterConfig); `one_at_a_time`: the app's lock of the network; `worded`: app.worded."""
    from geoloc.apps.localize.route import fused, route_plane
    from geoloc.sequence.odometry import parse_odometry

    try:  # once: a gallery whose tiles have no positions answers every route request with why
        plane, why = route_plane(localizer.places, route_config), None
    except (ValueError, AttributeError) as err:
        plane, why = None, str(err) if isinstance(err, ValueError) else "this localizer has no gallery places"

    @app.post("/localize/route", dependencies=[Depends(each_field_once("/localize/route", FILES, ("frames",)))])
    def localize_route(frames: Annotated[list[UploadFile], File(description=FRAMES)],
                       odometry: Annotated[UploadFile, File(description=ODOMETRY)],
                       form: Annotated[QueryForm, Form()], params: Annotated[QueryForm, Query()]) -> Response:
        if plane is None:
            raise HTTPException(409, f"this service cannot follow a route: {why}")
        if len(frames) > max_frames:
            raise HTTPException(413, f"{len(frames)} frames: a route request takes at most max_frames={max_frames}; "
                                     "send the route in parts")
        sent, where = sent_settings(form, params)
        try:
            query = localizer.parse(**sent)
        except QueryError as err:
            raise worded(err, where, max_seconds) from None
        try:
            motion = parse_odometry(odometry.file.read(), odometry.filename or "odometry")
        except ValueError as err:
            raise HTTPException(400, f"odometry: {err}") from None
        if len(motion) != len(frames):
            raise HTTPException(400, f"the odometry has {len(motion)} rows for {len(frames)} frames: a route needs "
                                     "one row per frame, in the frames' order")
        datas = [frame.file.read() for frame in frames]
        names = [frame.filename or f"frame {i}" for i, frame in enumerate(frames)]
        for data, name in zip(datas, names):  # every frame's header before the first answer
            try:
                localizer.check(*image_size(data, f"the upload {name!r}")[:2], query, name=f"the upload {name!r}")
            except QueryError as err:
                raise worded(err, where, max_seconds) from None
        with one_at_a_time:
            deadline = time.monotonic() + max_seconds  # the whole route's turn
            results = []
            try:
                for data, name in zip(datas, names):
                    rgb, _ = decode_upload(data, name, lambda width, height, name=name: localizer.check(
                        width, height, query, name=f"the upload {name!r}"))
                    results.append(localizer.localize(rgb, query, name=name, deadline=deadline))
            except QueryError as err:
                raise worded(err, where, max_seconds) from None
        body = {"frames": fused(plane, names, results, motion, route_config).lines,
                "answers": [r.to_json() for r in results], "tiles": named_tiles(localizer.places, results)}
        return Response(json.dumps(body, allow_nan=False), media_type="application/json")


def named_tiles(places, results) -> list[dict]:
    """The gallery tiles that `results` (the frames' answers) name in their top-k, each row once in the order first
    named: {"row", its centre (`places.kind`'s keys), "extent_m": the [height, width] metres it covers, or None in
    a gallery without ground extents (CVUSA's, CVACT's)}."""
    from geoloc.gallery.places import POSITION_KEYS  # on use, as add_route imports: importing this loads no torch

    keys, extent = POSITION_KEYS[places.kind], places.reference_extent_m
    rows = dict.fromkeys(int(hit["row"]) for result in results for hit in result.topk)
    return [{"row": row, **dict(zip(keys, map(float, places.reference_positions[row]))),
             "extent_m": None if extent is None else [float(v) for v in extent[row]]} for row in rows]
