"""VIGOR (Zhu et al., CVPR 2021) in its released layout -> RetrievalSplit. Nothing is decoded here.

    ROOT/<City>/panorama/<panoid>,<lat>,<lon>,.jpg
    ROOT/<City>/satellite/satellite_<lat>_<lon>.png
    ROOT/splits/<City>/satellite_list.txt                  one satellite file name per line
    ROOT/splits/<City>/same_area_balanced_{train,test}.txt
    ROOT/splits/<City>/pano_label_balanced.txt             every panorama of the city (cross-area)

A split line has 13 space-separated fields: the panorama file name, then 4 x (satellite file name, two pixel
offsets). The first satellite is the positive, the other three the semi-positives. The offsets are the satellite
centre minus the panorama position, (north, east) in satellite pixels: the panorama sits at row 320 + f1,
column 320 - f2 of the 640 px tile (VIGOR's evaluate_from_npy.py). They are checked to be numbers and otherwise
unused: metres come from the lat/lon in the file names.

Settings, as VIGOR's dataloader.py reads them:
- same_area: each of the four cities' same_area_balanced_{train,test}.txt;
- cross_area: pano_label_balanced.txt of New York + Seattle (train) or San Francisco + Chicago (test).
The references are every satellite in satellite_list.txt of the cities read, in file order, city by city.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.datasets.common import with_view
from geoloc.registry import register

CITIES = ("Chicago", "NewYork", "SanFrancisco", "Seattle")  # the released folder names
SETTINGS = ("same_area", "cross_area")
SPLITS = ("train", "test")
CROSS_AREA_CITIES = {"train": ("NewYork", "Seattle"), "test": ("Chicago", "SanFrancisco")}
FIELDS = 13


def default_cities(setting: str, split: str) -> tuple[str, ...]:
    _check_choice("setting", setting, SETTINGS)
    _check_choice("split", split, SPLITS)
    return CITIES if setting == "same_area" else CROSS_AREA_CITIES[split]


def split_file(setting: str, split: str) -> str:
    """The file, under ROOT/splits/<City>/, that lists the panoramas of (setting, split)."""
    _check_choice("setting", setting, SETTINGS)
    _check_choice("split", split, SPLITS)
    return f"same_area_balanced_{split}.txt" if setting == "same_area" else "pano_label_balanced.txt"


def vigor_split(root, setting: str = "same_area", split: str = "test", cities=None,
                splits_dir: str = "splits") -> RetrievalSplit:
    """Read (setting, split) for the given cities (default: the setting's, see default_cities). splits_dir names
    the folder of split files under root: `splits` as released, or e.g. `splits__corrected` (SliceMatch's
    re-computed labels, same format)."""
    root = Path(root)
    cities = tuple(default_cities(setting, split) if cities is None else cities)
    listing = split_file(setting, split)
    if not cities or len(set(cities)) != len(cities):
        raise ValueError(f"VIGOR cities must be a non-empty list without repeats, got {list(cities)}")
    references, ref_latlon, queries, q_latlon, positives, semi = [], [], [], [], [], []
    for city in cities:
        city_dir = root / splits_dir / city
        if not city_dir.is_dir():
            found = sorted(p.name for p in (root / splits_dir).glob("*") if p.is_dir())
            raise FileNotFoundError(
                f"VIGOR split folder {city_dir} not found (city {city!r}). dataset.root must be the VIGOR folder "
                f"holding <City>/panorama, <City>/satellite and splits/<City>/; cities found there: {found}.")
        index = {}
        for name, line_no in _satellite_list(city_dir / "satellite_list.txt"):
            if name in index:
                raise ValueError(f"{city_dir / 'satellite_list.txt'}:{line_no}: satellite {name} is listed twice")
            index[name] = len(references)
            references.append(root / city / "satellite" / name)
            ref_latlon.append(satellite_latlon(name, f"{city_dir / 'satellite_list.txt'}:{line_no}"))
        for pano, sats, line_no in _split_lines(city_dir / listing):
            where = f"{city_dir / listing}:{line_no}"
            missing = [s for s in sats if s not in index]
            if missing:
                raise ValueError(f"{where}: satellite {missing[0]} is not in {city_dir / 'satellite_list.txt'} "
                                 "(the split and the satellite list must come from the same release)")
            queries.append(root / city / "panorama" / pano)
            q_latlon.append(panorama_latlon(pano, where))
            positives.append(index[sats[0]])
            semi.append([index[s] for s in sats[1:]])
    if not queries:
        raise ValueError(f"VIGOR {setting} {split}: the {listing} files of {list(cities)} under {root / splits_dir} "
                         "list no panorama")
    return RetrievalSplit(
        name=f"vigor/{setting}/{split}", root=root, queries=queries, references=references,
        positives=np.asarray(positives, np.int64), semi_positives=np.asarray(semi, np.int64).reshape(len(semi), 3),
        query_latlon=np.asarray(q_latlon), reference_latlon=np.asarray(ref_latlon))


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
    out = [(line.strip(), k) for k, line in enumerate(path.read_text().splitlines(), 1) if line.strip()]
    if not out:
        raise ValueError(f"VIGOR satellite list {path} is empty")
    return out


def _split_lines(path: Path):
    """-> (panorama name, [positive, 3 semi-positives], line number) per non-empty line."""
    if not path.is_file():
        raise FileNotFoundError(f"VIGOR split file {path} not found (same_area reads "
                                "same_area_balanced_{train,test}.txt, cross_area pano_label_balanced.txt)")
    for k, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) != FIELDS:
            raise ValueError(f"{path}:{k}: expected {FIELDS} space-separated fields (panorama, then 4 x "
                             f"(satellite, two pixel offsets)), got {len(fields)}: {line.strip()[:120]!r}")
        for j in (2, 3, 5, 6, 8, 9, 11, 12):
            try:
                float(fields[j])
            except ValueError:
                raise ValueError(f"{path}:{k}: field {j + 1} should be a pixel offset, got {fields[j]!r}") from None
        yield fields[0], [fields[1], fields[4], fields[7], fields[10]], k


def _check_choice(key: str, value, choices) -> None:
    if value not in choices:
        raise ValueError(f"VIGOR {key} must be one of {list(choices)}, got {value!r}")


@register("dataset", "vigor")
def vigor(root: str | None, split: str, setting: str = "same_area", cities: list[str] | None = None,
          splits_dir: str = "splits", preset: str = "vigor_small", seed: int = 0, workers: int = 2) -> RetrievalSplit:
    """VIGOR in its released layout (module docstring); root=None renders the synthetic `vigor` layout."""
    split = "test" if split == "val" else split  # VIGOR has no val split; its papers validate on test
    if not root:
        from geoloc.synthetic import default_cache, ensure_dataset

        root = Path(ensure_dataset("vigor", default_cache() / f"vigor-{preset}-seed{seed}", preset=preset,
                                   train=None, val=None, seed=seed, workers=workers))
        if cities is None:  # a small preset renders fewer than four cities: the setting's that it has
            cities = [c for c in default_cities(setting, split) if (root / splits_dir / c).is_dir()]
    out = vigor_split(root, setting=setting, split=split, cities=cities, splits_dir=splits_dir)
    return with_view(out, "sphere")

