"""A dataset plug-in for task=mmdip: ROOT/<split>/{dynamic,static,mask,label}/<name>.png at dataset.image_size,
each name its own place (its dynamic view queries, its static view is the gallery entry)."""

from pathlib import Path

import cv2
import torch
from geoloc.registry import register
from geoloc.tasks.mmdip.datasets import class_fractions
from geoloc.tasks.mmdip.protocol import each_file_a_place


class ImageFolders(torch.utils.data.Dataset):
    def __init__(self, root: Path, split: str):
        self.folder = root / split
        self.names = sorted(p.name for p in (self.folder / "label").glob("*.png"))

    def __len__(self) -> int:
        return len(self.names)

    def read(self, kind: str, index: int) -> torch.Tensor:
        return torch.from_numpy(cv2.imread(str(self.folder / kind / self.names[index]), cv2.IMREAD_UNCHANGED))

    def __getitem__(self, key) -> dict:
        i = key[0] if isinstance(key, (tuple, list)) else key  # the trainer asks for (index, epoch)
        rgb = lambda kind: self.read(kind, i).flip(-1).permute(2, 0, 1).float() / 255  # noqa: E731  (BGR -> RGB)
        return {"dynamic": rgb("dynamic"), "static": rgb("static"), "mask": (self.read("mask", i) > 0).float()[None],
                "label": self.read("label", i).long(), "index": torch.tensor(i), "place": torch.tensor(i)}


class Reader:
    has_labels = True

    def __init__(self, root: Path, image_size):
        self.root, self.image_size = root, image_size

    def split(self, split: str, train: bool = False, seed: int = 0) -> ImageFolders:
        return ImageFolders(self.root, split)

    def place_protocol(self, split: str):
        return each_file_a_place("image_folders", self.root, split, self.image_size,
                                 lambda s: ImageFolders(self.root, s), self.has_labels)

    def class_fractions(self, split: str = "train", force: bool = False) -> list[float]:
        data = ImageFolders(self.root, split)
        files = [data.folder / "label" / name for name in data.names]
        maps = files, lambda i: data.read("label", i).numpy(), {"format": "image_folders", "split": split}
        return class_fractions(self.root, split, maps, force)


@register("mmdip_dataset", "image_folders")
def image_folders(root: str, image_size) -> Reader:
    return Reader(Path(root), image_size)
