"""What localize.py does: load the checkpoint and the gallery once, answer each image, write JSON lines and
pictures."""

from __future__ import annotations

import json
from pathlib import Path

from omegaconf import DictConfig

from geoloc.apps.localize.localizer import Localizer, read_street

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


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


def localize(cfg: DictConfig) -> list[dict]:
    images = images_of(Path(cfg.image))
    localizer = Localizer.load(cfg.ckpt, cfg.gallery, device=cfg.get("device", "auto"),
                               heading_steps=cfg.get("heading_steps", 36))
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    answers = []
    with open(out / "localize.jsonl", "a") as lines:
        for path in images:
            image = read_street(path)
            answer = localizer.localize(image, fov=cfg.fov, topk=cfg.topk, heading=cfg.get("heading"), path=path)
            if cfg.get("picture", True):
                from geoloc.apps.localize.picture import localization_figure

                answer["picture"] = str(localization_figure(answer, image, localizer.places, out / f"{path.stem}.png"))
            text = json.dumps(answer)
            print(text)
            lines.write(text + "\n")
            answers.append(answer)
    return answers
