"""`geoloc serve ckpt=PATH gallery=DIR ...`: load the localizer once, then serve it with uvicorn (one process)."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field

from omegaconf import MISSING

from geoloc.apps.query import QueryLimits, check_headings
from geoloc.apps.serve.app import MAX_BYTES, MAX_SECONDS, create_app
from geoloc.apps.serve.route_endpoint import MAX_FRAMES
from geoloc.sequence.particle_filter import FilterConfig

LIMITS = QueryLimits()
USAGE = f"""usage: geoloc serve ckpt=PATH gallery=DIR [host=127.0.0.1] [port=8000] [device=auto]
                    [heading_steps=K] [max_bytes={MAX_BYTES}] [max_seconds={MAX_SECONDS:g}]
                    [max_pixels={LIMITS.max_pixels}] [max_canvas_side={LIMITS.max_canvas_side}]
                    [max_headings={LIMITS.max_headings}] [max_topk={LIMITS.max_topk}] [api_docs=false]
                    [max_frames={MAX_FRAMES}] [route.KEY=VALUE ...]

  ckpt        a checkpoint written by train.py (best.pt)
  gallery     a gallery saved from it: python evaluate.py ckpt=PATH gallery.save=DIR
  host, port  where to listen (127.0.0.1: this machine only; 0.0.0.0: every interface)
  device      auto (the GPU when there is one, else the CPU), cpu, cuda, cuda:1 ...
  heading_steps  candidate headings tried when a request gives no heading (default: the checkpoint's
                 dataset.heading_steps, 36 unless it was trained otherwise: every 10 degrees)
  max_bytes   a larger request body gets 413
  max_seconds a request's turn at the network: its heading search stops past it with 503
  max_pixels, max_canvas_side, max_headings, max_topk
              what one image may cost (geoloc.apps.query.QueryLimits): its pixels and those of the 360° canvas
              a view of fov degrees is placed on (W·360/fov columns), the canvas's columns and rows, the
              candidate headings (heading_steps) and topk. An image over a limit gets 413 naming it, read from its
              header before it is decoded; heading_steps over max_headings is refused at start
  api_docs    serve FastAPI's /docs and /redoc pages, which load their scripts from cdn.jsdelivr.net (off: the
              API is described by /openapi.json)
  max_frames  the frames one POST /localize/route request may send (the whole route shares max_seconds)
  route.*     the sequence filter's settings for POST /localize/route (docs/sequence.md)

POST /localize (multipart field image; fov, topk, heading, heading_prior, abstain), POST /localize/route
(file fields frames, repeated, and odometry; the same settings), GET /health, GET / (the page:
open http://HOST:PORT/ in a browser) and GET /tiles/{{row}}; see docs/apps.md, "Query service"."""


@dataclass
class ServeConfig(QueryLimits):
    """`geoloc serve`'s keys (schema/serve: geoloc/conf/serve.yaml); the limits on one image are QueryLimits'."""

    ckpt: str = MISSING
    gallery: str = MISSING
    host: str = "127.0.0.1"
    port: int = 8000
    device: str | None = None  # None: the encoder's rule (auto)
    heading_steps: int | None = None  # None: the checkpoint's dataset.heading_steps
    max_bytes: int = MAX_BYTES
    max_seconds: float = MAX_SECONDS
    api_docs: bool = False  # FastAPI's /docs and /redoc, whose scripts come from a CDN
    max_frames: int = MAX_FRAMES  # the frames one POST /localize/route may send
    route: FilterConfig = field(default_factory=FilterConfig)  # the sequence filter of POST /localize/route

    def __post_init__(self):
        super().__post_init__()
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port must be in 0..65535, got {self.port}")
        if self.heading_steps is not None:
            check_headings(self.heading_steps, self)  # the Localizer's own check, before anything is loaded
        if self.max_bytes < 1:
            raise ValueError(f"max_bytes must be >= 1, got {self.max_bytes}")
        if not self.max_seconds > 0:
            raise ValueError(f"max_seconds must be > 0, got {self.max_seconds}")
        if self.max_frames < 1:
            raise ValueError(f"max_frames must be >= 1, got {self.max_frames}")


def main(args: list[str]) -> int:
    import uvicorn

    from geoloc.launch.hydra_hooks import compose_checked

    cfg = compose_checked("serve", ServeConfig, args, "serve")  # geoloc/conf/serve.yaml
    from geoloc.apps.localize import Localizer  # torch and the model code: only once the arguments are good

    try:  # once, before the first request: every request shares this model and gallery
        localizer = Localizer.load(cfg.ckpt, cfg.gallery, device=cfg.device, heading_steps=cfg.heading_steps,
                                   limits=cfg.limits())
    except (FileNotFoundError, ValueError) as err:  # its message names the file or the key, and what to do
        print(f"geoloc serve: {err}", file=sys.stderr)
        return 2
    app = create_app(localizer, max_bytes=cfg.max_bytes, max_seconds=cfg.max_seconds, api_docs=cfg.api_docs,
                     route=cfg.route, max_frames=cfg.max_frames)
    uvicorn.run(app, host=cfg.host, port=cfg.port)  # one worker process: a second would load a second model
    return 0
