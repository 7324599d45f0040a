"""Weights that ship inside the package: `backbone.weights_path=geoloc:NAME` reads `geoloc/weights/NAME.pt`.

Each file has a card beside it, `NAME.json`: the backbone it fits (name, width, batchnorm), the recipe, seed and
data version it was trained with, and the file's sha256, checked before the file is read (docs/backbones.md,
"Weights shipped with geoloc"). Nothing here touches the network.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

PREFIX = "geoloc:"
FOLDER = Path(__file__).resolve().parent.parent / "weights"


class PackagedWeightsError(FileNotFoundError):
    pass


def is_packaged(weights_path: str | None) -> bool:
    """Whether `weights_path` names weights shipped with geoloc (`geoloc:NAME`) rather than a file."""
    return isinstance(weights_path, str) and weights_path.startswith(PREFIX)


def names() -> list[str]:
    """The names `geoloc:NAME` accepts: every card in geoloc/weights/."""
    return sorted(p.stem for p in FOLDER.glob("*.json"))


def card(weights_path: str) -> dict:
    """The card of `geoloc:NAME`; PackagedWeightsError naming the shipped ones for an unknown name."""
    name = weights_path[len(PREFIX):] if is_packaged(weights_path) else weights_path
    path = FOLDER / f"{name}.json"
    if not name or "/" in name or not path.is_file():
        raise PackagedWeightsError(f"backbone.weights_path={weights_path!r}: geoloc ships no weights called {name!r}. "
                                   f"Shipped: {', '.join(PREFIX + n for n in names()) or 'none'}.")
    return json.loads(path.read_text())


def packaged_file(weights_path: str, backbone: str) -> Path:
    """The checked file of `geoloc:NAME` for a `backbone` (registry name) backbone: refused when the card is for
    another backbone, the file is missing (a checkout without it: reinstall geoloc), or its sha256 differs."""
    info = card(weights_path)
    if info["backbone"]["name"] != backbone:
        raise ValueError(f"backbone.weights_path={weights_path!r} holds a {info['backbone']['name']} trunk, not a "
                         f"{backbone} one: set backbone={info['backbone']['name']} or choose other weights.")
    path = FOLDER / info["file"]
    if not path.is_file():
        raise PackagedWeightsError(f"backbone.weights_path={weights_path!r}: {path} is missing from this install. "
                                   f"Reinstall geoloc (pip install --force-reinstall), whose wheel holds it.")
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    if digest != info["sha256"]:
        raise ValueError(f"backbone.weights_path={weights_path!r}: {path} has sha256 {digest[:16]}..., its card "
                         f"{info['sha256'][:16]}...: the file is damaged or was replaced. Reinstall geoloc.")
    return path
