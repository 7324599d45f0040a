"""VIGOR (Zhu et al., CVPR 2021) in its released layout -> RetrievalSplit. Nothing is decoded here.

    ROOT/<City>/panorama/<panoid>,<lat>,<lon>,.jpg
    ROOT/<City>/satellite/satellite_<lat>_<lon>.png
    ROOT/splits/<City>/satellite_list.txt                  one satellite file name per line
    ROOT/splits/<City>/same_area_balanced_{train,test}.txt
    ROOT/splits/<City>/pano_label_balanced.txt             every panorama of the city (cross-area)

A split line has 13 space-separated fields: the panorama file name, then 4 x (satellite file name, two pixel
offsets). The first satellite is the positive, the other three the semi-positives. The offsets are the satellite
centre minus the panorama position, (north, east) in pixels of the 640 px tile: the panorama sits at row 320 + f1,
column 320 - f2 (CCVPE's datasets.py). They give each query's position in its tiles (RetrievalSplit.query_tile_px,
query_semi_tile_px), with the per-city metres per pixel of CCVPE's train_VIGOR.py (METRES_PER_PX); metre
distances between places come from the lat/lon in the file names.

Two label sets give the offsets (docs/conventions.md "VIGOR tile scale and label sets"):
- `vigor_corrected`: SliceMatch's re-computed labels, in `splits__corrected/<City>/`, files named
  `same_area_balanced_{train,test}__corrected.txt` and `pano_label_balanced__corrected.txt` beside
  `satellite_list.txt`: pixels at each city's true scale, read as released. Some semi-positive offsets lie
  outside the 640 px tile (at the true scale the panorama is not in that tile); they are kept as the file gives
  them, and only positions inside a tile are ever used.
- `vigor_original`: VIGOR's own files. Their offsets were computed at 0.114 m a pixel in every city (VIGOR's
  evaluate_from_npy.py), so they are converted to the city's true pixels: offset * 0.114 / METRES_PER_PX[city].
`splits_dir=null` (the default) reads `splits__corrected` when the root has it, else `splits`; the files' names say
which set a folder holds. The split records it (RetrievalSplit.tile_labels), and every metre figure names it.

geoloc's synthetic vigor tree (geoloc/synthetic/vigor_layout.py) renders tiles of its own size and scale, which its
marker gives (geoloc.synthetic.tile_geometry), and writes the offsets unrounded in ROOT/geoloc_offsets.json
(geoloc/data/tile_offsets.py), which are used instead of the rounded ones when present. A tree holding that file
without a complete marker is an unfinished render, and is refused.

Settings, as VIGOR's dataloader.py reads them:
- same_area: each of the four cities' same_area_balanced_{train,test}.txt;
- cross_area: pano_label_balanced.txt of New York + Seattle (train) or San Francisco + Chicago (test).
The references are every satellite in satellite_list.txt of the cities read, in file order, city by city.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from geoloc.data.list_files import list_lines, refuse_repeats
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.data.tile_offsets import OFFSETS_FILE, read_offsets
from geoloc.datasets.common import check_split, tile_frame, with_view
from geoloc.registry import register

CITIES = ("Chicago", "NewYork", "SanFrancisco", "Seattle")  # the released folder names
SETTINGS = ("same_area", "cross_area")
SPLITS = ("train", "test")
CROSS_AREA_CITIES = {"train": ("NewYork", "Seattle"), "test": ("Chicago", "SanFrancisco")}
FIELDS = 13
TILE_PX = 640  # the released satellite tiles are 640 x 640
# ground metres per tile pixel in each city (CCVPE's train_VIGOR.py)
METRES_PER_PX = {"NewYork": 0.113248, "Seattle": 0.100817, "SanFrancisco": 0.118141, "Chicago": 0.111262}
CORRECTED = "__corrected"  # SliceMatch's file-name suffix
SPLITS_DIRS = ("splits__corrected", "splits")  # splits_dir=null: the first of these that the root holds
# VIGOR's original offsets were made at this scale in every city (its evaluate_from_npy.py, "0.114 is resolution in
# meter"); SliceMatch's corrected ones at each city's own (METRES_PER_PX)
ORIGINAL_METRES_PER_PX = 0.114


def default_cities(setting: str, split: str) -> tuple[str, ...]:
    _check_choice("setting", setting, SETTINGS)
    check_split("VIGOR", split, SPLITS)
    return CITIES if setting == "same_area" else CROSS_AREA_CITIES[split]


def split_file(setting: str, split: str) -> str:
    """The file, under ROOT/splits/<City>/, that lists the panoramas of (setting, split)."""
    _check_choice("setting", setting, SETTINGS)
    check_split("VIGOR", split, SPLITS)
    return f"same_area_balanced_{split}.txt" if setting == "same_area" else "pano_label_balanced.txt"


def vigor_split(root, setting: str = "same_area", split: str = "test", cities=None,
                splits_dir: str | None = None) -> RetrievalSplit:
    """Read (setting, split) for the given cities (default: the setting's, see default_cities). splits_dir names
    the folder of split files under root: `splits` as released, or `splits__corrected` (SliceMatch's re-computed
    labels: the same format, file names ending in `__corrected`); None: the corrected folder where the root has
    one (module docstring)."""
    root = Path(root)
    splits_dir = splits_dir or default_splits_dir(root)
    cities = tuple(default_cities(setting, split) if cities is None else cities)
    listing = split_file(setting, split)
    if not cities or len(set(cities)) != len(cities):
        raise ValueError(f"VIGOR cities must be a non-empty list without repeats, got {list(cities)}")
    tile_px, synthetic_scale = tile_frame(root, TILE_PX)
    truth = read_offsets(root)
    if truth is not None and synthetic_scale is None:  # geoloc's own file, which no release holds
        from geoloc.synthetic.generate import MARKER
        from geoloc.synthetic.geometry import unfinished_render

        raise ValueError(unfinished_render(root, f"it holds {OFFSETS_FILE}, which only geoloc's renderer writes, but "
                                                 f"no complete {MARKER}"))
    references, ref_latlon, ref_scale, queries, q_latlon, positives, semi, offsets = [], [], [], [], [], [], [], []
    label_sets = {}
    for city in cities:
        city_dir = root / splits_dir / city
        if not city_dir.is_dir():
            found = sorted(p.name for p in (root / splits_dir).glob("*") if p.is_dir())
            raise FileNotFoundError(
                f"VIGOR split folder {city_dir} not found (city {city!r}). dataset.root must be the VIGOR folder "
                f"holding <City>/panorama, <City>/satellite and splits/<City>/; cities found there: {found}.")
        index = {}
        for name, line_no in _satellite_list(city_dir / "satellite_list.txt"):
            index[name] = len(references)
            references.append(root / city / "satellite" / name)
            ref_latlon.append(satellite_latlon(name, f"{city_dir / 'satellite_list.txt'}:{line_no}"))
        ref_scale += [synthetic_scale or METRES_PER_PX.get(city, np.nan)] * (len(references) - len(ref_scale))
        path = _listing(city_dir, listing)
        labels = ("synthetic" if synthetic_scale else
                  "vigor_corrected" if path.stem.endswith(CORRECTED) else "vigor_original")
        label_sets.setdefault(labels, path)
        to_true_px = original_to_true_px(city) if labels == "vigor_original" else 1.0
        for pano, sats, deltas, line_no in _split_lines(path):
            where = f"{path}:{line_no}"
            missing = [s for s in sats if s not in index]
            if missing:
                raise ValueError(f"{where}: satellite {missing[0]} is not in {city_dir / 'satellite_list.txt'} "
                                 "(the split and the satellite list must come from the same release)")
            queries.append(root / city / "panorama" / pano)
            q_latlon.append(panorama_latlon(pano, where))
            positives.append(index[sats[0]])
            semi.append([index[s] for s in sats[1:]])
            offsets.append(np.multiply(deltas, to_true_px) if truth is None
                           else _true_offsets(truth, city, pano, sats, deltas, where))
    if not queries:
        raise ValueError(f"VIGOR {setting} {split}: the {listing} files of {list(cities)} under {root / splits_dir} "
                         "list no panorama")
    if len(label_sets) > 1:
        found = ", ".join(f"{name} ({path})" for name, path in label_sets.items())
        raise ValueError(f"VIGOR {setting} {split}: the cities' split files hold different label sets: {found}. "
                         "Read every city from one folder of one set (dataset.splits_dir)")
    deltas = np.asarray(offsets, np.float64)  # Q x 4 x (north, east) pixels, tile centre minus panorama
    position = np.stack([tile_px / 2 + deltas[..., 0], tile_px / 2 - deltas[..., 1]], -1)  # (row, col)
    scale = np.asarray(ref_scale, np.float64)
    return RetrievalSplit(
        name=f"vigor/{setting}/{split}", root=root, queries=queries, references=references,
        positives=np.asarray(positives, np.int64), semi_positives=np.asarray(semi, np.int64).reshape(len(semi), 3),
        query_latlon=np.asarray(q_latlon), reference_latlon=np.asarray(ref_latlon),
        reference_size_px=np.full((len(references), 2), tile_px, np.int64),
        reference_metres_per_px=None if np.isnan(scale).any() else scale,  # a city of unknown scale: none
        query_tile_px=position[:, 0], query_semi_tile_px=position[:, 1:], tile_labels=next(iter(label_sets)))


def original_to_true_px(city: str) -> float:
    """The factor from VIGOR's original offsets (made at 0.114 m a pixel) to `city`'s true pixels; 1 for a city
    of unknown scale, whose offsets are kept as written (and give no metres)."""
    return ORIGINAL_METRES_PER_PX / METRES_PER_PX[city] if city in METRES_PER_PX else 1.0


def default_splits_dir(root: Path) -> str:
    """The folder of split files read when dataset.splits_dir is null: SliceMatch's corrected labels where the root
    has them, else VIGOR's originals."""
    return next((name for name in SPLITS_DIRS if (root / name).is_dir()), SPLITS_DIRS[-1])


def _listing(city_dir: Path, listing: str) -> Path:
    """The split file as released: `listing`, or SliceMatch's `<stem>__corrected.txt` in a corrected folder."""
    plain, corrected = city_dir / listing, city_dir / listing.replace(".txt", f"{CORRECTED}.txt")
    if plain.is_file() and corrected.is_file():
        raise ValueError(f"{city_dir} holds both {plain.name} and {corrected.name}; keep the original labels in "
                         f"splits/ and SliceMatch's in splits__corrected/ (dataset.splits_dir picks the folder)")
    return corrected if corrected.is_file() else plain


def _true_offsets(truth: dict, city: str, pano: str, sats: list[str], rounded: list, where: str) -> list:
    """The unrounded offsets of one split line, checked against its rounded ones."""
    try:
        out = [[float(v) for v in truth[city][pano][s]] for s in sats]
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{where}: {OFFSETS_FILE} has no offsets for panorama {pano} and its tiles; it belongs to "
                         "another rendering: delete it and load the synthetic dataset again") from None
    if np.abs(np.asarray(out) - np.asarray(rounded)).max() > 0.5 + 1e-6:
        raise ValueError(f"{where}: the offsets in {OFFSETS_FILE} ({out}) do not round to the split line's "
                         f"({rounded}); it belongs to another rendering: delete it and load the dataset again")
    return out


def panorama_latlon(name: str, where: str = "") -> tuple[float, float]:
    """`<panoid>,<lat>,<lon>,.jpg` -> (lat, lon)."""
    parts = name.split(",")
    try:
        if len(parts) < 4:
            raise ValueError
        return float(parts[-3]), float(parts[-2])
    except ValueError:
        raise ValueError(f"{where}: panorama name {name!r} is not '<panoid>,<lat>,<lon>,.jpg'") from None


def satellite_latlon(name: str, where: str = "") -> tuple[float, float]:
    """`satellite_<lat>_<lon>.png` -> (lat, lon)."""
    stem = name.rsplit(".", 1)[0]
    parts = stem.split("_")
    try:
        if len(parts) != 3 or parts[0] != "satellite":
            raise ValueError
        return float(parts[1]), float(parts[2])
    except ValueError:
        raise ValueError(f"{where}: satellite name {name!r} is not 'satellite_<lat>_<lon>.png'") from None


def _satellite_list(path: Path):
    """-> (name, line number) per non-empty line."""
    if not path.is_file():
        raise FileNotFoundError(f"VIGOR satellite list {path} not found; every splits/<City>/ folder of the "
                                "release holds one")
    out = [(line, k) for k, line in list_lines(path, "VIGOR satellite list")]
    if not out:
        raise ValueError(f"VIGOR satellite list {path} is empty")
    refuse_repeats(path, out, "satellite")
    return out


def _split_lines(path: Path) -> list:
    """-> (panorama name, [positive, 3 semi-positives], 4 x [north, east] pixel offsets, line number) per non-empty
    line; a panorama is listed once."""
    if not path.is_file():
        raise FileNotFoundError(f"VIGOR split file {path} not found (same_area reads "
                                "same_area_balanced_{train,test}.txt, cross_area pano_label_balanced.txt; "
                                f"SliceMatch's corrected folder the same names ending in {CORRECTED}.txt)")
    out = []
    for k, line in list_lines(path, "VIGOR split file"):
        fields = line.split()
        if len(fields) != FIELDS:
            raise ValueError(f"{path}:{k}: expected {FIELDS} space-separated fields (panorama, then 4 x "
                             f"(satellite, two pixel offsets)), got {len(fields)}: {line[:120]!r}")
        offsets = []
        for j in (2, 3, 5, 6, 8, 9, 11, 12):
            try:
                offsets.append(float(fields[j]))
            except ValueError:
                raise ValueError(f"{path}:{k}: field {j + 1} should be a pixel offset, got {fields[j]!r}") from None
        if not np.isfinite(offsets).all():
            raise ValueError(f"{path}:{k}: the pixel offsets must be finite numbers, got {offsets}")
        out.append((fields[0], fields[1::3], [offsets[i:i + 2] for i in range(0, 8, 2)], k))
    refuse_repeats(path, [(pano, k) for pano, _, _, k in out], "panorama")
    return out


def _check_choice(key: str, value, choices) -> None:
    if value not in choices:
        raise ValueError(f"VIGOR {key} must be one of {list(choices)}, got {value!r}")


@register("dataset", "vigor")
def vigor(root: str | None, split: str, setting: str = "same_area", cities: list[str] | None = None,
          splits_dir: str | None = None, preset: str = "vigor_small", seed: int = 0,
          workers: int = 2) -> RetrievalSplit:
    """VIGOR in its released layout (module docstring); root=None renders the synthetic `vigor` layout."""
    split = "test" if split == "val" else split  # VIGOR has no val split; its papers validate on test
    if not root:
        from geoloc.synthetic import default_cache, ensure_dataset

        root = Path(ensure_dataset("vigor", default_cache() / f"vigor-{preset}-seed{seed}", preset=preset,
                                   train=None, val=None, seed=seed, workers=workers))
        if cities is None:  # a small preset renders fewer than four cities: the setting's that it has
            folder = root / (splits_dir or default_splits_dir(root))
            cities = [c for c in default_cities(setting, split) if (folder / c).is_dir()]
    out = vigor_split(root, setting=setting, split=split, cities=cities, splits_dir=splits_dir)
    return with_view(out, "sphere")

