"""A saved gallery's folder: written whole or not at all, and opened only by what it was built for.

`python evaluate.py ckpt=... gallery.save=DIR` writes into DIR:
- gallery.pt: the index (geoloc.eval.search_index.GalleryIndex.save);
- gallery.json: what built it: the weights' `model_fingerprint` (engine/checkpoint.py) and the `ckpt` path, the
  `dataset` reader, the `split`, its absolute `root` and `references_sha256` (the ordered reference paths,
  places.split_record); the index `kind` and knobs; the `reference_spread` measured when it was built;
- references.jsonl, queries.jsonl: the places (places.py);
- calibration.json: the answers' confidence (confidence.py), or why there is none.
A FAISS index's codes lie in gallery.faiss beside gallery.pt, an ivfpq_disk index's float16 rows in
gallery.<i>.f16 (GalleryIndex.save).

A part of a gallery built across jobs (gallery.py `build_part`) is such a folder too, with a `part` record in
gallery.json: a codebook (`role: codebook`, no rows, its index file's `codebook_sha256`) or a shard (`role: shard`,
`shard_index`, `num_shards`, its rows `start`..`stop` of the split's `split_references`, the `codebook_sha256` it
was filled from, and `index_sha256`: the digest of each of its own index files). `open_gallery` refuses parts;
`open_codebook` opens a codebook for a shard; `geoloc gallery merge` joins shards into a gallery
(gallery_shards.py).

Saving writes every file into a hidden folder beside DIR (`.DIR.<random>.tmp`) and renames that folder to DIR, so
DIR holds a whole gallery or none: an interrupted save leaves the old gallery as it was. An existing gallery is
replaced only with `gallery.overwrite=true`, by exchanging the two folders in one rename (Linux `renameat2`; where
the file system cannot, the old folder is renamed aside first), then removing the old one. A folder that holds
anything but a gallery is never replaced.

Opening (`open_gallery`: evaluate.py gallery.load=, localize.py and geoloc serve) checks, before anything is
searched: gallery.json (JSON, fields), the weights' fingerprint against the checkpoint's, for evaluate.py the split
being scored (dataset, split, root, reference count and order), then gallery.pt against gallery.json (count, dim)
and every line of references.jsonl and queries.jsonl. Each problem raises a ConfigError naming the file and what to
do (a missing file FileNotFoundError).
"""

from __future__ import annotations

import ctypes
import errno
import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from geoloc.config import ConfigError
from geoloc.data.retrieval_split import RetrievalSplit
from geoloc.engine.checkpoint import file_sha256, umask
from geoloc.eval.search_index import GalleryIndex, faiss_file, index_files
from geoloc.gallery.confidence import check_record
from geoloc.gallery.index_settings import capped_nlist
from geoloc.gallery.places import Places, read_places, split_record, write_places

INFO, INDEX, CALIBRATION = "gallery.json", "gallery.pt", "calibration.json"
# gallery.json's fields and their JSON types ("positions" is null or a string, checked by read_places)
FIELDS = {"num_references": int, "dim": int, "backend": str, "kind": str, "ckpt": str, "model_fingerprint": str,
          "dataset": str, "split": str, "root": str, "query_view": str, "references_sha256": str,
          "reference_spread": (int, float)}
# what binds a gallery to the split it was built from
SPLIT_KEYS = ("dataset", "split", "root", "num_references", "references_sha256")


@dataclass
class SavedGallery:
    """A checked gallery folder: its gallery.json, the index and the places."""

    folder: Path
    info: dict
    index: GalleryIndex
    places: Places
    calibration: dict | None = None  # calibration.json; None: saved without one (uncalibrated)


def rebuild(folder: Path, ckpt=None) -> str:
    return (f"Rebuild it: python evaluate.py ckpt={ckpt or 'CKPT'} [dataset=... dataset.root=...] "
            f"gallery.save={folder} gallery.overwrite=true")


# ---- saving ----------------------------------------------------------------------------------------------------
def check_target(folder: str | Path, overwrite: bool) -> None:
    """Refuse `gallery.save=folder` when it holds a gallery (unless `overwrite`) or anything else (always)."""
    folder = Path(folder)
    if not folder.exists():
        return
    if not folder.is_dir():
        raise ConfigError(f"gallery.save={folder} is a file, not a folder: choose a folder for the gallery")
    held = sorted(p.name for p in folder.iterdir())
    if not held:
        return
    if not {INFO, INDEX} & set(held):
        raise ConfigError(f"gallery.save={folder} holds files that are not a gallery ({', '.join(held[:5])}): "
                          "choose a new or empty folder (gallery.overwrite=true replaces only a gallery)")
    if not overwrite:
        raise ConfigError(f"gallery.save={folder} already holds a gallery{_built_from(folder)}: add "
                          "gallery.overwrite=true to replace it, or choose another gallery.save folder")


def _built_from(folder: Path) -> str:
    try:
        info = json.loads((folder / INFO).read_text())
        return f" (built by {info['ckpt']} from {info['split']} of {info['root']})"
    except (OSError, ValueError, TypeError, KeyError):
        return ""


def save_gallery(folder: str | Path, index: GalleryIndex, split: RetrievalSplit, record: dict,
                 overwrite: bool = False, rows=None, calibration: dict | None = None) -> dict:
    """Write the gallery of `split` (its references `rows`, default all, in order, are `index`'s rows) into
    `folder`, whole or not at all; `record` holds what built it (ckpt, model_fingerprint, dataset,
    reference_spread; a part's `part`); `calibration` is written as calibration.json. Returns gallery.json."""
    def fill(tmp: Path) -> dict:
        index.save(tmp / INDEX)
        info = {"num_references": len(index), "dim": index.dim, "backend": index.backend, "kind": index.kind,
                **index.params, **record, **write_places(tmp, split, rows)}
        if info.get("part", {}).get("role") == "codebook":
            info["codebook_sha256"] = file_sha256(faiss_file(tmp / INDEX))
        if info.get("part", {}).get("role") == "shard":  # the merge checks that the files are still these
            info["index_sha256"] = index_digests(tmp / INDEX)
        if calibration is not None:
            write_calibration(tmp, calibration)
        return info

    return write_gallery_folder(folder, fill, overwrite)


def write_calibration(folder: Path, record: dict) -> None:
    """`record` as the calibration.json of the gallery being written in `folder`."""
    (folder / CALIBRATION).write_text(json.dumps(record, indent=2, allow_nan=False) + "\n")


def index_digests(path: Path) -> dict[str, str]:
    """{file name: sha256} of the files an index is saved in (GalleryIndex.save): `path` (gallery.pt) and, for a
    FAISS index, the index file beside it (and an ivfpq_disk index's float16 rows)."""
    return {f.name: file_sha256(f) for f in index_files(path) if f.is_file()}


def write_gallery_folder(folder: str | Path, fill, overwrite: bool = False) -> dict:
    """Write a gallery folder whole or not at all: `fill(tmp)` writes the index and places (and any other file)
    into a temporary folder beside `folder` and returns gallery.json's record, which is written last; then the
    folder moves into place."""
    folder = Path(folder)
    check_target(folder, overwrite)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".tmp", dir=folder.parent))
    try:
        os.chmod(tmp, 0o777 & ~umask())  # mkdtemp's 0700 would keep a service run by another user out
        info = fill(tmp)
        (tmp / INFO).write_text(json.dumps(info, indent=2) + "\n")
        _move_into_place(tmp, folder, overwrite)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # after an exchange, tmp holds the old gallery
    return info



def _move_into_place(tmp: Path, folder: Path, overwrite: bool) -> None:
    if overwrite and folder.is_dir() and any(folder.iterdir()):
        check_target(folder, overwrite)  # again: it may have changed while the gallery was built
        if _exchange(tmp, folder):
            return
        old = tmp.with_suffix(".old")
        os.rename(folder, old)  # a kill before the next rename leaves the old gallery here, whole
        os.rename(tmp, folder)
        shutil.rmtree(old, ignore_errors=True)
        return
    try:
        os.rename(tmp, folder)  # onto a missing or empty folder only: a non-empty one refuses
    except OSError as err:
        if err.errno in (errno.ENOTEMPTY, errno.EEXIST):
            raise ConfigError(f"gallery.save={folder}: another gallery was saved there while this one was built; "
                              "it was kept. Add gallery.overwrite=true to replace it, or choose another "
                              "gallery.save folder") from None
        raise


def _exchange(a: Path, b: Path) -> bool:
    """Swap two folders in one step (renameat2 RENAME_EXCHANGE); False where the OS or file system cannot."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    if ctypes.get_errno() in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(ctypes.get_errno(), f"could not move the new gallery {a} into place at {b}")


# ---- opening ---------------------------------------------------------------------------------------------------
def read_info(folder: Path, ckpt=None) -> dict:
    """gallery.json of `folder`, its fields checked."""
    path = Path(folder) / INFO
    if not path.is_file():
        raise FileNotFoundError(f"{folder} holds no saved gallery ({INFO}). Build one from the split whose references "
                                f"you want to search: python evaluate.py ckpt={ckpt or 'CKPT'} [dataset=... "
                                f"dataset.root=DIR] gallery.save={folder}")
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        what = "empty" if path.stat().st_size == 0 else f"not complete JSON ({err})"
        raise ConfigError(f"{path} is {what}: the save that wrote it was interrupted, or it was edited. "
                          f"{rebuild(folder, ckpt)}") from None
    if not isinstance(info, dict):
        raise ConfigError(f"{path} holds a JSON {type(info).__name__}, not a gallery record. {rebuild(folder, ckpt)}")
    bad = [k for k, kind in FIELDS.items() if not isinstance(info.get(k), kind) or isinstance(info.get(k), bool)]
    if bad:
        raise ConfigError(f"{path} lacks {', '.join(bad)} (or holds another type): the gallery was saved by an "
                          f"older geoloc, which did not record what built it, or the file was edited. "
                          f"{rebuild(folder, ckpt)}")
    return info


def check_weights(folder: Path, info: dict, fingerprint: str, ckpt) -> None:
    """The one check that a gallery was built by the weights that will encode the queries."""
    if info["model_fingerprint"] != fingerprint:
        raise ConfigError(f"the gallery in {folder} was built with other weights ({info['ckpt']}) than {ckpt}: its "
                          f"descriptors would not match the queries. Use ckpt={info['ckpt']}, or rebuild the "
                          f"gallery: python evaluate.py ckpt={ckpt} [dataset=... dataset.root=...] "
                          f"gallery.save={folder} gallery.overwrite=true (or a new folder)")


def check_split(folder: Path, info: dict, split: RetrievalSplit, dataset: str, ckpt) -> None:
    """Refuse a gallery built from another split than the one being scored: gallery row j must be its reference j."""
    here = {"dataset": dataset, "num_references": split.num_references, **split_record(split)}
    differs = [f"{k} {info[k]!r} (gallery) vs {here[k]!r} (this evaluation)"
               for k in SPLIT_KEYS if k != "references_sha256" and info[k] != here[k]]
    if not differs and info["references_sha256"] != here["references_sha256"]:
        differs = ["the reference list: the same number of references, in another order or other files "
                   "(references_sha256 differs)"]
    if differs and info.get("appended"):
        differs.append(f"it holds references appended from {len(info['appended'])} other part(s) (geoloc gallery "
                       "append), so it is the gallery of no one split")
    if differs:
        raise ConfigError(f"the gallery in {folder} was built from another split than the one scored here: "
                          f"{'; '.join(differs)}. Its row j would not be this split's reference j, so the recall "
                          f"would be wrong. Evaluate the split it was built from, or rebuild it for this one: "
                          f"python evaluate.py ckpt={ckpt} [dataset=... dataset.root=...] gallery.save={folder} "
                          f"gallery.overwrite=true")


def open_gallery(folder: str | Path, fingerprint: str, ckpt, device=None, split: RetrievalSplit | None = None,
                 dataset: str | None = None) -> SavedGallery:
    """The gallery in `folder`, refused unless the weights of fingerprint `fingerprint` (checkpoint `ckpt`, named in
    messages) built it and, when `split` is given (evaluate.py; `dataset` its reader), it was built from that
    split. The torch backend's descriptors go to `device`."""
    folder = Path(folder)
    info = read_info(folder, ckpt)
    if info.get("part"):
        part = info["part"]
        what = (f"shard {part.get('shard_index')} of {part.get('num_shards')}" if part.get("role") == "shard"
                else "the codebook")
        raise ConfigError(f"{folder} holds {what} of a gallery built across jobs, not a whole gallery: join the "
                          f"shards first (geoloc gallery merge SHARD_DIR... out=DIR) and open DIR")
    check_weights(folder, info, fingerprint, ckpt)
    if split is not None:
        check_split(folder, info, split, dataset, ckpt)
    if not (folder / INDEX).is_file():
        raise FileNotFoundError(f"the gallery in {folder} lacks {INDEX}. {rebuild(folder, ckpt)}")
    try:
        index = GalleryIndex.load(folder / INDEX, device=device)
        if (len(index), index.dim) != (info["num_references"], info["dim"]):
            raise ConfigError(f"{folder / INDEX} holds {len(index)} references of dim {index.dim}, but {folder / INFO} "
                              f"records {info['num_references']} of dim {info['dim']}: one of them was replaced")
        places = read_places(folder, info)
        calibration = read_calibration(folder)
    except ValueError as err:  # ConfigError included: the file is named, the way out is added here
        raise ConfigError(f"{err}. {rebuild(folder, ckpt)}") from err
    return SavedGallery(folder, info, index, places, calibration)


def open_codebook(folder: str | Path, fingerprint: str, ckpt, kind: str | None, params: dict) -> SavedGallery:
    """The codebook in `folder` (gallery.train_only=true), refused unless it was trained by these weights for an
    index of `kind` (None: gallery.kind=auto, the codebook's) with the knobs `params` as gallery.* gives them (the
    ones that shape its quantisers; nlist as capped on the references it trained on). It may have been trained on
    another split's references: new references appended to a gallery (gallery/append.py) are filled from the
    gallery's codebook."""
    folder = Path(folder)
    info = read_info(folder, ckpt)
    if info.get("part", {}).get("role") != "codebook":
        raise ConfigError(f"gallery.codebook={folder} is not a codebook: write one with python evaluate.py "
                          f"ckpt={ckpt} gallery.train_only=true gallery.save={folder} (with the shards' gallery.kind "
                          "and knobs)")
    check_weights(folder, info, fingerprint, ckpt)
    wanted = {**({} if kind is None else {"kind": kind}), **params,
              "nlist": capped_nlist(params["nlist"], info["part"]["split_references"])}
    differs = [f"{k} {info.get(k)!r} (codebook) vs {v!r} (here)" for k, v in wanted.items()
               if k in ("kind", "nlist", "m", "nbits", "coarse_m", "hnsw_m") and info.get(k) != v]
    if differs:
        raise ConfigError(f"the codebook in {folder} was trained for another index: {'; '.join(differs)}. Give "
                          f"every shard the codebook's gallery.kind and knobs, or train a codebook for these")
    try:
        index = GalleryIndex.load(folder / INDEX, mmap=False)  # no rows: small, and copied for each shard
    except ValueError as err:
        raise ConfigError(f"{err}. Write the codebook again: python evaluate.py ckpt={ckpt} gallery.train_only=true "
                          f"gallery.save={folder} gallery.overwrite=true") from err
    return SavedGallery(folder, info, index, None)


def read_calibration(folder: Path) -> dict | None:
    """calibration.json of `folder`, checked (confidence.check_record), or None when there is none."""
    path = folder / CALIBRATION
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ConfigError(f"{path} is not complete JSON ({err})") from None
    try:
        return check_record(record)
    except ValueError as err:
        raise ConfigError(f"{path} {err}") from None
