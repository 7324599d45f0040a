"""What localize.py does: load the checkpoint and the gallery once, answer each image, write JSON lines and
pictures."""

from __future__ import annotations

import json
from pathlib import Path

from dataclasses import dataclass

from omegaconf import MISSING, DictConfig

from geoloc.apps.localize.localizer import Localizer, read_street
from geoloc.config import checked

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


@dataclass
class LocalizeConfig:
    """localize.py's keys (conf/localize.yaml extends this node: schema/localize)."""

    ckpt: str = MISSING  # a checkpoint written by train.py
    gallery: str = MISSING  # a gallery saved from it: python evaluate.py ckpt=... gallery.save=DIR
    image: str = MISSING  # one image, or a folder of them
    out: str = MISSING  # where localize.jsonl and the pictures go (default: a new folder under outputs/localize/)
    topk: int = 5
    fov: float = 360.0  # the image's horizontal field of view in degrees: 360 = a panorama; less = a street photo
    heading: float | None = None  # its bearing when known (degrees clockwise from north; CVUSA panoramas: 0)
    heading_steps: int | None = None  # candidate headings tried when heading is null; null: the checkpoint's own
    device: str = "auto"
    picture: bool = True  # one PNG per image: the query, the top-k tiles and a map of the candidates


def images_of(target: Path) -> list[Path]:
    """The image itself, or a folder's images (sorted by name)."""
    if target.is_dir():
        found = sorted(p for p in target.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not found:
            raise FileNotFoundError(f"image={target} is a folder without .jpg/.jpeg/.png files")
        return found
    if not target.is_file():
        raise FileNotFoundError(f"image={target} does not exist: give an image file or a folder of images")
    return [target]


def localize(section: DictConfig) -> list[dict]:
    """Each image's answer as written to localize.jsonl (LocalizationResult.to_json)."""
    cfg = checked(section, LocalizeConfig, "localize.py")
    images = images_of(Path(cfg.image))
    localizer = Localizer.load(cfg.ckpt, cfg.gallery, device=cfg.device, heading_steps=cfg.heading_steps)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    answers = []
    with open(out / "localize.jsonl", "a") as lines:
        for path in images:
            image = read_street(path)
            result = localizer.localize(image, fov=cfg.fov, topk=cfg.topk, heading=cfg.heading, path=path)
            if cfg.picture:
                from geoloc.apps.localize.picture import localization_figure

                result.picture = str(localization_figure(result, image, localizer.places, out / f"{path.stem}.png"))
            answer = result.to_json()
            text = json.dumps(answer)
            print(text)
            lines.write(text + "\n")
            answers.append(answer)
    return answers
