"""A gallery grown by new references without a rebuild (`geoloc gallery append GALLERY_DIR PART_DIR... out=DIR`).

GALLERY_DIR is a gallery whose index was filled from a codebook (a merge of shards, or an earlier append); each
PART_DIR is a shard folder written from the new references by the same checkpoint, filled from that same codebook
(evaluate.py on the new split, `gallery.codebook=CODEBOOK_DIR gallery.num_shards=S gallery.shard_index=i
gallery.save=PART_DIR`), or a gallery appended the same way. The parts' indexes are merged after the gallery's
(GalleryIndex.merge: codes moved, nothing encoded or trained again; an ivfpq_disk gallery's float16 rows are linked,
not rewritten), and their references.jsonl follow the gallery's (a part's paths on the gallery's root: relative where its files lie
under it, else absolute).

The binding to the reference list is updated: `references_sha256` is that of the joined list, `num_references` its
length, and `appended` records each split that was added (dataset, split, root, its references and their count).
An appended gallery is no longer the gallery of one split: evaluate.py gallery.load= refuses to score a split
against it (its row j is not the split's reference j); localize.py and geoloc serve answer from it. The top-1
confidence was fitted against the old gallery, so it is dropped (confidence.across_jobs); the refiner's stays.
"""

from __future__ import annotations

import json
from pathlib import Path

from geoloc.config import ConfigError
from geoloc.eval.search_index import GalleryIndex
from geoloc.gallery.confidence import across_jobs
from geoloc.gallery.folder import INDEX, read_calibration, read_info, write_calibration, write_gallery_folder
from geoloc.gallery.places import rebased, reference_paths_sha256
from geoloc.gallery.shards import SHARED, check_index_files, shard_index

# what a part shares with the gallery it is appended to: what the shards of one gallery share (the weights, the
# descriptors' view and places, the index and its codebook), less the split, which a part adds anew
APPENDABLE = tuple(k for k in SHARED if k not in ("dataset", "split", "root", "references_sha256"))


def read_parts(gallery: Path, parts: list[Path]) -> tuple[dict, list[tuple[Path, dict]]]:
    """(gallery.json of `gallery`, [(part, its gallery.json)]), checked to be appendable."""
    info = read_info(gallery)
    if info.get("part"):
        raise ConfigError(f"{gallery} holds a part of a gallery, not a gallery: merge its shards first (geoloc "
                          f"gallery merge SHARD_DIR... out=DIR), then append to DIR")
    if not info.get("codebook_sha256"):
        raise ConfigError(f"the gallery in {gallery} trained its own codebook in one job, so no part can be filled "
                          f"from it: build it from a codebook (gallery.train_only=true, then shard jobs with "
                          f"gallery.codebook=CODEBOOK_DIR and geoloc gallery merge) to append to it later")
    if not parts:
        raise ConfigError("give the parts to append: geoloc gallery append GALLERY_DIR PART_DIR... out=DIR")
    read = []
    for part in parts:
        part_info = read_info(part)
        role = (part_info.get("part") or {}).get("role")
        if role == "codebook":
            raise ConfigError(f"{part} holds a codebook, not references: append the shard folders encoded from it")
        if role == "shard":
            check_index_files(part, part_info)
        differs = [f"{k} {part_info.get(k)!r} vs {info.get(k)!r}" for k in APPENDABLE if part_info.get(k) != info.get(k)]
        if differs:
            raise ConfigError(f"{part} cannot be appended to the gallery in {gallery}: {'; '.join(differs)}. A part "
                              f"must be encoded by the same checkpoint into the same index kind and knobs, filled "
                              f"from the gallery's codebook (gallery.codebook=CODEBOOK_DIR)")
        read.append((Path(part), part_info))
    return info, read


def reference_lines(folder: Path, root: str, new_root: str) -> list[dict]:
    """The lines of `folder`'s references.jsonl (its split's root: `root`), their paths rebased on `new_root`."""
    lines = [json.loads(line) for line in (folder / "references.jsonl").read_text(encoding="utf-8").splitlines()
             if line.strip()]
    return lines if root == new_root else [{**line, "path": rebased(line["path"], root, new_root)} for line in lines]


def check_new_references(gallery: tuple[Path, dict], parts: list[tuple[Path, dict]]) -> list[list[dict]]:
    """The reference lines of the gallery and of each part (paths on the gallery's root), refused where a part
    lists a reference that the gallery or an earlier part holds already: it would be two rows of one place."""
    root = gallery[1]["root"]
    lines = [reference_lines(folder, info["root"], root) for folder, info in (gallery, *parts)]
    paths, seen = [line["path"] for line in lines[0]], set()
    new = [(part, [line["path"] for line in part_lines]) for (part, _), part_lines in zip(parts, lines[1:])]
    for part, listed in new:
        again = seen.intersection(listed)
        if again:
            raise ConfigError(f"{part} lists {len(again)} reference(s) that another part holds already (e.g. "
                              f"{sorted(again)[0]}): give each part once")
        seen.update(listed)
    held = next((p for p in paths if p in seen), None)
    if held is not None:
        raise ConfigError(f"the gallery in {gallery[0]} holds {held} already, which a part lists again: append "
                          "only references it does not hold")
    return lines


def appended_record(part: Path, info: dict) -> list[dict]:
    """What `part` adds to the binding: its own split, or the splits a part that was itself appended holds."""
    own = {k: info.get(k) for k in ("dataset", "split", "root", "references_sha256")}
    split_rows = (info.get("part") or {}).get("split_references")
    whole = split_rows is None or split_rows == info["num_references"]
    return [{**own, "num_references": info["num_references"], "whole_split": whole, "from": str(part.resolve())},
            *info.get("appended", [])]


def append_galleries(gallery: str | Path, parts: list[str | Path], out: str | Path,
                     overwrite: bool = False) -> tuple[dict, dict]:
    """Write the gallery in `gallery` with the parts' references after its own into `out` (which may be `gallery`
    itself with `overwrite`); returns its gallery.json and calibration.json records."""
    gallery, parts = Path(gallery), [Path(p) for p in parts]
    info, read = read_parts(gallery, parts)
    lines = check_new_references((gallery, info), read)
    paths = [line["path"] for folder_lines in lines for line in folder_lines]
    try:
        index = GalleryIndex.load(gallery / INDEX, mmap=False)  # the one that grows
    except ValueError as err:
        raise ConfigError(f"the gallery in {gallery}: {err}") from None
    for part, part_info in read:  # one part at a time in memory besides the growing index
        index.merge(shard_index(part, part_info))
    if len(paths) != len(index):
        raise ConfigError(f"the references.jsonl of {gallery} and the parts list {len(paths)} references, their "
                          f"indexes hold {len(index)}: a folder was edited. Rebuild the part that disagrees")
    calibration = across_jobs(read_calibration(gallery))

    def fill(tmp: Path) -> dict:
        index.save(tmp / INDEX)
        with open(tmp / "references.jsonl", "w", encoding="utf-8") as joined:
            joined.writelines(json.dumps(line) + "\n" for folder_lines in lines for line in folder_lines)
        (tmp / "queries.jsonl").write_bytes((gallery / "queries.jsonl").read_bytes())
        write_calibration(tmp, calibration)
        spreads = [info["reference_spread"], *(i["reference_spread"] for _, i in read)]
        return {**{k: v for k, v in info.items() if k != "appended"}, "num_references": len(index),
                "references_sha256": reference_paths_sha256(paths), "reference_spread": min(spreads),
                "appended": [*info.get("appended", []), *(r for p, i in read for r in appended_record(p, i))]}

    return write_gallery_folder(out, fill, overwrite), calibration
