"""Dynamic-scene datasets (MMDIP): the synthetic `dynamic` layout, the authors' 4-panel CARLA PNGs and the
Empty Cities 3-panel images. Formats: docs/dynamic_layout.md and docs/conventions.md "Dynamic-scene data". The
registered readers that task=mmdip builds by `dataset.name` (readers.py) hand these out, with their place protocols
and class fractions.

Every reader returns dicts of tensors: `dynamic` and `static` (3 x H x W float in [0, 1]), `mask` (1 x H x W,
1 where a dynamic object is seen), `index`, and where the format has them `label` (H x W int64 static classes
0..7), `place` and `is_query`. Images of another size than `image_size` are resized (bilinear; labels nearest)
with a one-time message; wrong channel counts and labels outside the class set are refused naming the file.
"""

from __future__ import annotations

import json
import logging
import warnings
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from geoloc.data import label_census
from geoloc.data.list_files import csv_rows, refuse_repeats
from geoloc.data.validate import check_files, require_complete, run_checks
from geoloc.engine.sampling import item_rng, split_key

log = logging.getLogger(__name__)

NUM_CLASSES = 8
SPLIT_COLUMNS = ("sample", "place", "role")  # what the reader takes of a splits/<split>.csv row
STATIC_CLASSES = ("None", "Buildings", "Fences", "Others", "Roadlines", "Road", "Sidewalk", "Vegetation")
# CARLA 0.8 tag -> the paper's 8 classes; 4 (pedestrian) and 10 (vehicle) are the dynamic tags
# (docs/conventions.md "Dynamic-scene data").
CARLA_TO_STATIC = {0: 0, 1: 1, 2: 2, 3: 3, 4: 3, 5: 3, 10: 3, 11: 3, 12: 3, 6: 4, 7: 5, 8: 6, 9: 7}
CARLA_DYNAMIC_TAGS = (4, 10)
_CARLA_LUT = np.array([CARLA_TO_STATIC[t] for t in range(13)], np.uint8)
EMPTY_CITIES_PANEL_WH = (800, 600)


class DataFormatError(ValueError):
    """A file of a dynamic-scene dataset does not have the expected format."""


def read_rgb(path: Path) -> np.ndarray:
    require_complete(path)  # a truncated JPEG would decode with a grey fill and only a libjpeg warning
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DataFormatError(f"{path}: missing or does not decode")
    if img.ndim != 3 or img.shape[2] != 3:
        got = 1 if img.ndim == 2 else img.shape[2]
        raise DataFormatError(f"{path}: expected a 3-channel RGB image, got {got} channel(s) (shape {img.shape})")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_label(path: Path, num_classes: int = NUM_CLASSES) -> np.ndarray:
    lab = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if lab is None:
        raise DataFormatError(f"{path}: missing or does not decode")
    if lab.ndim != 2:
        raise DataFormatError(f"{path}: expected a single-channel label image, got shape {lab.shape}")
    check_label_values(lab, num_classes, path)
    return lab


def _label_problem(path: Path) -> str | None:
    try:
        read_label(path)
    except DataFormatError as err:
        return str(err).removeprefix(f"{path}: ")
    return None


def check_label_values(lab: np.ndarray, num_classes: int, path) -> None:
    if lab.size and int(lab.max()) >= num_classes:
        bad = np.unique(lab[lab >= num_classes])[:5].tolist()
        raise DataFormatError(f"{path}: label values {bad} lie outside the class set 0..{num_classes - 1}")


class _Resizer:
    """Resizes to `image_size` (H, W) when it differs, saying so once per dataset."""

    def __init__(self, image_size, name: str):
        self.hw = tuple(image_size) if image_size else None
        self.name, self.warned = name, False

    def __call__(self, img: np.ndarray, path, nearest: bool = False) -> np.ndarray:
        if self.hw is None or img.shape[:2] == self.hw:
            return img
        if not self.warned:
            log.warning("%s: %s is %dx%d, resizing to %dx%d (dataset.image_size)", self.name, path,
                        img.shape[0], img.shape[1], *self.hw)
            self.warned = True
        interp = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA
        return cv2.resize(img, self.hw[::-1], interpolation=interp)


def _image_tensor(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1).float() / 255.0


def _sample(dynamic, static, mask, label=None, flip=False, **extra) -> dict[str, torch.Tensor]:
    arrays = {"dynamic": dynamic, "static": static, "mask": mask, "label": label}
    if flip:
        arrays = {k: (None if v is None else v[:, ::-1]) for k, v in arrays.items()}
    out = {"dynamic": _image_tensor(arrays["dynamic"]), "static": _image_tensor(arrays["static"]),
           "mask": torch.from_numpy(np.ascontiguousarray(arrays["mask"] > 0)).float()[None]}
    if label is not None:
        out["label"] = torch.from_numpy(np.ascontiguousarray(arrays["label"])).long()
    out.update({k: torch.tensor(v) for k, v in extra.items()})
    return out


class DynamicDataset(Dataset):
    """The synthetic `dynamic` layout: one row of `splits/{split}.csv` per sample (docs/dynamic_layout.md).

    `roles` selects rows ("reference", "query" or both); `augment` flips horizontally with p = 0.5, seeded per
    (seed, epoch, index) so a step's data does not depend on workers or resumes.
    """

    def __init__(self, root, split: str = "train", image_size=None, roles=("reference", "query"),
                 augment: bool = False, seed: int = 0, check: str = "exists"):
        self.root = Path(root)
        marker = self.root / "geoloc_synthetic.json"
        if marker.is_file():
            layout = json.loads(marker.read_text()).get("layout")
            if layout != "dynamic":
                raise DataFormatError(f"{self.root} holds the synthetic '{layout}' layout, not 'dynamic'")
        csv_path = self.root / "splits" / f"{split}.csv"
        if not csv_path.is_file():
            raise FileNotFoundError(f"{csv_path} not found: dataset.root must be a `dynamic` layout folder "
                                    f"(python data_prep/synthetic.py --layout dynamic --out DIR ...)")
        rows = _split_rows(csv_path)
        rows = [r for r in rows if r["role"] in roles]
        if not rows:
            raise ValueError(f"{csv_path} has no rows with role in {tuple(roles)}")
        self.samples = [r["sample"] for r in rows]
        self.places = np.array([int(r["place"]) for r in rows])
        self.is_query = np.array([r["role"] == "query" for r in rows])
        self.augment, self.seed = augment, seed
        self.resize = _Resizer(image_size, f"dynamic/{split}")
        check_files([self._path(d, s) for s in self.samples for d in ("rgb_dynamic", "rgb_static", "label_static",
                                                                      "mask_dynamic")], self.root, split, check)
        if check != "off":  # an id outside the class set fails now, naming the file, not at the first validation
            run_checks([self._path("label_static", s) for s in self.samples], self.root, split,
                       f"labels<{NUM_CLASSES}", _label_problem, what=f"not label maps of classes 0..{NUM_CLASSES - 1}")

    def _path(self, folder: str, sample: str) -> Path:
        return self.root / folder / f"{sample}.png"

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, key) -> dict[str, torch.Tensor]:
        rng = item_rng(self.seed, key)
        index, _ = split_key(key)
        s = self.samples[index]
        dynamic = self.resize(read_rgb(self._path("rgb_dynamic", s)), s)
        static = self.resize(read_rgb(self._path("rgb_static", s)), s)
        label = self.resize(read_label(self._path("label_static", s)), s, nearest=True)
        mask = cv2.imread(str(self._path("mask_dynamic", s)), cv2.IMREAD_GRAYSCALE)
        if mask is None:
            raise DataFormatError(f"{self._path('mask_dynamic', s)}: missing or does not decode")
        mask = self.resize(mask, s, nearest=True)
        flip = self.augment and rng.random() < 0.5
        return _sample(dynamic, static, mask, label, flip, index=index, place=int(self.places[index]),
                       is_query=bool(self.is_query[index]))


def _split_rows(csv_path: Path) -> list[dict[str, str]]:
    """The rows of a `dynamic` layout's splits/<split>.csv as {column: value}; each sample once."""
    lines = csv_rows(csv_path, "dynamic split file")
    header = lines[0][1] if lines else []
    missing = [c for c in SPLIT_COLUMNS if c not in header]
    if missing:
        raise ValueError(f"{csv_path}: the first line must name the columns {list(SPLIT_COLUMNS)} (and any others), "
                         f"got {header}; missing {missing}")
    rows = []
    for k, fields in lines[1:]:
        if len(fields) != len(header):
            raise ValueError(f"{csv_path}:{k}: expected {len(header)} fields ({','.join(header)}), got {len(fields)}")
        rows.append(dict(zip(header, fields)))
    refuse_repeats(csv_path, [(r["sample"], k) for r, (k, _) in zip(rows, lines[1:])], "sample")
    return rows


def panel_folder(root: Path, split: str | None) -> Path:
    """The folder a panel reader lists: ROOT/<split>/ when it exists, else ROOT itself."""
    root = Path(root)
    return root / split if split and (root / split).is_dir() else root


def _panel_files(root: Path, split: str | None) -> list[Path]:
    folder = panel_folder(root, split)
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if not files:
        raise FileNotFoundError(f"no PNG/JPG images in {folder}")
    return files


def _split_panels(img: np.ndarray, n: int, path: Path) -> list[np.ndarray]:
    if img.shape[1] % n:
        raise DataFormatError(f"{path}: width {img.shape[1]} does not split into {n} equal panels")
    w = img.shape[1] // n
    return [img[:, i * w : (i + 1) * w] for i in range(n)]


def carla_tags_to_static(tags: np.ndarray, path) -> np.ndarray:
    """CARLA 0.8 tag map -> the paper's 8 static classes; tags above 12 are refused naming the file."""
    if tags.size and int(tags.max()) > 12:
        bad = np.unique(tags[tags > 12])[:5].tolist()
        raise DataFormatError(f"{path}: CARLA tags {bad} lie outside the CARLA 0.8 tag set 0..12")
    return _CARLA_LUT[tags]


class CarlaFourPanelDataset(Dataset):
    """The authors' release: one PNG per sample, dynamic RGB | dynamic seg | static RGB | static seg.

    Seg panels hold CARLA 0.8 tags (in every channel, as CARLA's raw output writes them in red; the red channel
    is read). The dynamic mask is where the dynamic seg panel shows tag 4 (pedestrian) or 10 (vehicle). Each
    file is its own place: its dynamic panel is the query, its static panel the reference.
    """

    def __init__(self, root, split: str | None = None, image_size=None, augment: bool = False, seed: int = 0):
        self.files = _panel_files(Path(root), split)
        self.resize = _Resizer(image_size, "carla4")
        self.augment, self.seed = augment, seed

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, key) -> dict[str, torch.Tensor]:
        index, _ = split_key(key)
        path = self.files[index]
        dyn, dyn_seg, sta, sta_seg = _split_panels(read_rgb(path), 4, path)
        dyn_tags = dyn_seg[..., 0]
        mask = np.isin(dyn_tags, CARLA_DYNAMIC_TAGS).astype(np.uint8) * 255
        carla_tags_to_static(dyn_tags, path)  # refuse a bad dynamic panel too
        label = carla_tags_to_static(sta_seg[..., 0], path)
        flip = self.augment and item_rng(self.seed, key).random() < 0.5
        return _sample(self.resize(dyn, path), self.resize(sta, path), self.resize(mask, path, nearest=True),
                       self.resize(label, path, nearest=True), flip, index=index, place=index)


class EmptyCitiesDataset(Dataset):
    """Empty Cities (Bescos et al.): one image per sample, dynamic | static | dynamic mask, each 800 x 600.

    No labels, so it is for evaluation only. Each file is its own place: its dynamic panel is the query, its
    static panel the reference (the place protocol), and the static panel is the recovery ground truth.
    """

    def __init__(self, root, split: str | None = None, image_size=None):
        self.files = _panel_files(Path(root), split)
        self.resize = _Resizer(image_size, "emptycities")
        self.warned = False

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, key) -> dict[str, torch.Tensor]:
        index, _ = split_key(key)
        path = self.files[index]
        dyn, sta, mask = _split_panels(read_rgb(path), 3, path)
        if dyn.shape[1::-1] != EMPTY_CITIES_PANEL_WH and not self.warned:
            log.warning("%s: panels are %dx%d, Empty Cities panels are 800x600", path, dyn.shape[1], dyn.shape[0])
            self.warned = True
        mask = (mask.max(axis=2) > 127).astype(np.uint8) * 255
        return _sample(self.resize(dyn, path), self.resize(sta, path), self.resize(mask, path, nearest=True),
                       index=index, place=index)


def dynamic_label_maps(root: Path, split: str) -> tuple[list[Path], Callable[[int], np.ndarray], dict]:
    """(label files, read(i) -> H x W class ids, source description) of a `dynamic` split, for the class census."""
    ds = DynamicDataset(root, split, check="off")
    files = [ds._path("label_static", s) for s in ds.samples]
    return files, lambda i: read_label(files[i]), {"format": "dynamic", "split": split, "class_map": None}


def carla4_label_maps(root: Path, split: str) -> tuple[list[Path], Callable[[int], np.ndarray], dict]:
    """The same for the authors' 4-panel PNGs: their static seg panels, CARLA tags mapped to the 8 classes."""
    ds = CarlaFourPanelDataset(root, split)
    class_map = {str(t): c for t, c in CARLA_TO_STATIC.items()}
    return ds.files, lambda i: ds[i]["label"].numpy(), {"format": "carla4", "split": split, "class_map": class_map}


def class_fractions(root, split: str, label_maps, force: bool = False) -> list[float]:
    """The split's class fractions r_c, from root/class_fractions.json while it matches the label files on disk.

    `label_maps` is (files, read, source) of the split (dynamic_label_maps, carla4_label_maps); a reader's
    class_fractions() calls this. Recounted (and stored) when the file is missing, older than the labels or made
    from other files (geoloc.data.label_census); the count reads every label map, so an id outside the
    class set fails naming the file. Raises DataFormatError when one class covers every pixel (nothing to segment);
    warns for each class with no pixel at all (eq. 1 then gives it the largest weight, 1/ln(1.02) = 50.5, but
    phase 1 never sees it).
    """
    root = Path(root)
    files, read, source = label_maps
    path = root / label_census.FILE_NAME
    try:
        fractions = label_census.stored_or_counted(path, files, read, STATIC_CLASSES, source, force)
    except DataFormatError:
        raise
    except ValueError as err:  # the census's own checks, with the file named
        raise DataFormatError(str(err)) from err
    present = [c for c, f in enumerate(fractions) if f > 0]
    if len(present) == 1:
        raise DataFormatError(
            f"{path}: every labelled pixel of the {split} split ({len(files)} files under {root}) is class "
            f"{present[0]} ({STATIC_CLASSES[present[0]]}), so phase 1 has nothing to learn and would score PA/MIoU "
            f"without meaning. Are the label maps class ids 0..{NUM_CLASSES - 1} (not colours or a binary mask)?")
    absent = [STATIC_CLASSES[c] for c, f in enumerate(fractions) if f == 0]
    if absent:
        warnings.warn(f"{path}: classes {absent} have no pixel in the {split} labels of {root}: eq. 1 gives them "
                      "the largest weight (50.5), but phase 1 never learns them, and they drop out of the MIoU "
                      "unless predicted")
    return fractions
