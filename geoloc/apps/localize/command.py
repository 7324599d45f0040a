"""What localize.py does: load the checkpoint and the gallery once, answer each image, write JSON lines and
pictures.

The outputs never touch the inputs or another run: `out=` may not be a folder that holds an input image (a figure
`<name>.png` would replace an input, and be read as one by the next run on that folder); each image's figure is
named after its whole file name (`a.jpg.png`, `a.png.png`), so two images never share one; and the run holds the
lock of its `out=` folder (geoloc/launch/rundir.py) while it writes, so a second localize.py, or a training, cannot
write there at the same time.

The keys are parsed once, here, into a LocalizeConfig and the QuerySettings of every image (`parse`), which the
localizer makes its own once (`Localizer.settings`: the default heading, abstain, refine); nothing below parses them
again. Every image's header is checked (its size against the limits and the gallery's query view) before the first
is answered, so a folder holding an image the query cannot take is refused, naming that file, before any work.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

from omegaconf import MISSING, DictConfig, OmegaConf

from geoloc.apps.localize.localizer import Localizer
from geoloc.apps.query import SETTINGS, QueryError, QueryLimits, QuerySettings, check_settings, image_size
from geoloc.config import ConfigError, checked
from geoloc.data.io import read_rgb
from geoloc.launch.run_log import run_log
from geoloc.launch.rundir import claimed
from geoloc.sequence.particle_filter import FilterConfig

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


@dataclass
class LocalizeConfig(QueryLimits, QuerySettings):
    """localize.py's keys (geoloc/conf/localize.yaml extends this node: schema/localize): the query's settings are
    QuerySettings', the limits on one image QueryLimits' (geoloc/apps/query.py, the same keys as `geoloc serve`'s)."""

    ckpt: str = MISSING  # a checkpoint written by train.py
    gallery: str = MISSING  # a gallery saved from it: python evaluate.py ckpt=... gallery.save=DIR
    image: str = MISSING  # one image, or a folder of them
    out: str = MISSING  # where localize.jsonl and the pictures go (default: a new folder under outputs/localize/)
    heading_steps: int | None = None  # candidate headings of a heading search; null: the checkpoint's own
    device: str = "auto"
    picture: bool = True  # one PNG per image: the query, the top-k tiles and a map of the candidates
    # a route: image= a folder of frames (in name order) and odometry= its odometry.csv (docs/sequence.md); the
    # answers are fused into a track, route.jsonl, with route.png; null: every image on its own
    odometry: str | None = None
    route: FilterConfig = field(default_factory=FilterConfig)  # the sequence filter's settings (docs/sequence.md)


def images_of(target: Path) -> list[Path]:
    """The image itself, or a folder's image files (sorted by name)."""
    if target.is_dir():
        found = sorted(p for p in target.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
        if not found:
            raise FileNotFoundError(f"image={target} is a folder without .jpg/.jpeg/.png files")
        return found
    if not target.is_file():
        raise FileNotFoundError(f"image={target} does not exist: give an image file or a folder of images")
    return [target]


def figure_name(image: Path) -> str:
    """The figure of `image` in out/: its whole file name + .png, so a.jpg and a.png get a figure each."""
    return f"{image.name}.png"


def refuse_out_holding_inputs(out: Path, images: list[Path]) -> None:
    """out= must not be a folder an input image lies in: the figures (PNG images themselves) would land among the
    inputs, could replace one (a.png.png may be an input too) and would be read as inputs by the next run there."""
    folders = {p.parent.resolve() for p in images}
    if out.resolve() in folders:
        raise ConfigError(f"out={out} is the folder of the input images (image=...): the figures and localize.jsonl "
                          "would be written among them, and read as images by the next run on that folder. Give "
                          "another out= folder (or leave it out: a new folder under outputs/localize/)")


def parse(section: DictConfig) -> tuple[LocalizeConfig, QuerySettings]:
    """localize.py's keys, checked once: all but the query's settings against LocalizeConfig, then the settings as
    given, as the service's form fields are (fov=abc names fov), topk within max_topk."""
    cfg = checked(OmegaConf.masked_copy(section, [key for key in section if key not in SETTINGS]), LocalizeConfig,
                  "localize.py")
    try:
        query = check_settings(**{key: section.get(key) for key in SETTINGS}, max_topk=cfg.max_topk)
    except QueryError as err:
        raise ConfigError(f"localize.py: {err}") from None
    return replace(cfg, **vars(query)), query


def localize(section: DictConfig) -> list[dict]:
    """Each image's answer as written to localize.jsonl (LocalizationResult.to_json)."""
    cfg, given = parse(section)
    images = images_of(Path(cfg.image))
    out = Path(cfg.out)
    refuse_out_holding_inputs(out, images)
    odometry = None if cfg.odometry is None else read_route_odometry(Path(cfg.odometry), images)
    answers = []
    with claimed(out, role="localization", key="out"), run_log(out, "localize"):  # one writer per folder; a failed
        # start leaves none; the log holds what the run printed
        localizer = Localizer.load(cfg.ckpt, cfg.gallery, device=cfg.device, heading_steps=cfg.heading_steps,
                                   limits=cfg)
        try:  # abstain needs a calibrated gallery: refused before any image is read
            query = localizer.settings(given)
        except QueryError as err:
            raise ConfigError(f"localize.py: {err}") from None
        if odometry is not None:  # a gallery that cannot carry a route is refused before any frame
            from geoloc.apps.localize.route import route_plane, track

            try:
                plane = route_plane(localizer.places, cfg.route)
            except ValueError as err:
                raise ConfigError(f"localize.py odometry={cfg.odometry}: {err}") from None
        for path in images:  # every header before the first answer: an image the query cannot take stops no run midway
            localizer.check(*image_size(path.read_bytes(), str(path))[:2], query, name=str(path))
        results = []
        with open(out / "localize.jsonl", "a") as lines:
            for path in images:
                image = read_rgb(path)
                result = localizer.localize(image, query, path=path)
                if cfg.picture:
                    from geoloc.apps.localize.picture import localization_figure

                    picture = localization_figure(result, image, localizer.places, out / figure_name(path))
                    result.picture = str(picture)
                answer = result.to_json()
                text = json.dumps(answer)
                print(text)
                lines.write(text + "\n")
                answers.append(answer)
                results.append(result)
        if odometry is not None:
            track(plane, images, results, odometry, cfg.route, out, cfg.picture)
    return answers


def read_route_odometry(path: Path, images: list[Path]):
    """The route's odometry, one row per frame (ConfigError naming the file otherwise), read before any frame."""
    from geoloc.sequence.odometry import read_odometry

    try:
        odometry = read_odometry(path)
    except (OSError, ValueError) as err:
        raise ConfigError(f"localize.py odometry={path}: {err}") from None
    if len(odometry) != len(images):
        raise ConfigError(f"localize.py odometry={path} has {len(odometry)} rows for {len(images)} frames in "
                          f"image={images[0].parent}: a route needs one row per frame (frames in name order)")
    return odometry
