"""One gallery from the shards that independent jobs encoded (`geoloc gallery merge SHARD_DIR... out=DIR`).

Each shard folder (evaluate.py gallery.num_shards=S gallery.shard_index=i gallery.save=SHARD_DIR) holds the index of
one contiguous block of the split's references and their references.jsonl; the merge checks that the shards are
the S blocks of one gallery, each once: the same weights (`model_fingerprint`), split (dataset, split, root,
`references_sha256`), index kind and knobs and codebook (`codebook_sha256`), shard indices 0..S-1 with rows that
follow each other, and index files that are the ones each shard job wrote (`index_sha256`). It then joins their
indexes with FAISS's `merge_from` (GalleryIndex.merge: the stored codes are moved, nothing is re-encoded or
re-trained; one shard at a time is read besides the merged index), their references.jsonl in order (whose paths
must hash to the split's `references_sha256`), takes the queries.jsonl they share, computes the reference spread
from their moments, keeps the refiner's confidence that shard 0's job fitted (the top-1 confidence is fitted against
the whole gallery, which no job held: the merged gallery's calibration.json says it is uncalibrated, and why), and
writes one gallery folder (gallery_folder.write_gallery_folder: whole or not at all).
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

from geoloc.config import ConfigError
from geoloc.engine.checkpoint import file_sha256
from geoloc.eval.search_index import GalleryIndex, index_files
from geoloc.gallery.confidence import across_jobs
from geoloc.gallery.folder import (INDEX, INFO, read_calibration, read_info, write_calibration,
                                                   write_gallery_folder)
from geoloc.gallery.places import reference_paths_sha256

# what every shard of one gallery shares: the weights, the split, the index and its codebook
SHARED = ("model_fingerprint", "dataset", "split", "root", "references_sha256", "query_view", "positions", "dim",
          "backend", "kind", "nlist", "m", "nbits", "coarse_m", "hnsw_m", "ef_construction", "codebook_sha256")


def shard_command(folder, index, count) -> str:
    return (f"python evaluate.py ckpt=CKPT [dataset=... dataset.root=...] gallery.num_shards={count} "
            f"gallery.shard_index={index} gallery.save={folder} [gallery.codebook=CODEBOOK_DIR]")


def rebuild_shard(folder: Path, info: dict) -> str:
    """The way out for a shard folder that cannot be merged: its job run again."""
    return f"Rebuild it with {shard_command(folder, info['part']['shard_index'], info['part']['num_shards'])}"


def read_shards(folders: list[Path]) -> list[tuple[Path, dict]]:
    """(folder, gallery.json) of each shard, in shard order, checked to be the shards of one gallery, each once."""
    if not folders:
        raise ConfigError("give the shard folders to merge: geoloc gallery merge SHARD_DIR... out=DIR")
    shards = []
    for folder in folders:
        info = read_info(shard_folder(folder))
        part = info.get("part") or {}
        if part.get("role") != "shard":
            what = "a codebook" if part.get("role") == "codebook" else "a whole gallery"
            raise ConfigError(f"{folder} holds {what}, not a shard: merge only the folders that the shard jobs "
                              f"wrote (evaluate.py gallery.num_shards=S gallery.shard_index=i gallery.save=DIR)")
        check_moments(folder, info)
        check_index_files(folder, info)
        shards.append((Path(folder), info))
    first, ref = shards[0]
    for folder, info in shards[1:]:
        differs = [f"{k} {info.get(k)!r} vs {ref.get(k)!r}" for k in SHARED if info.get(k) != ref.get(k)]
        for k in ("num_shards", "split_references"):
            if info["part"][k] != ref["part"][k]:
                differs.append(f"{k} {info['part'][k]} vs {ref['part'][k]}")
        if differs:
            raise ConfigError(f"the shard in {folder} is not of the same gallery as the one in {first}: "
                              f"{'; '.join(differs)}. Every shard must be encoded by the same checkpoint from the "
                              f"same split and reference list, into the same index kind filled from the same codebook: "
                              f"rebuild the foreign one with {shard_command(folder, info['part']['shard_index'], ref['part']['num_shards'])}")
    count = ref["part"]["num_shards"]
    by_index: dict[int, Path] = {}
    for folder, info in shards:
        i = info["part"]["shard_index"]
        if i in by_index:
            raise ConfigError(f"{by_index[i]} and {folder} both hold shard {i} of {count}: give each shard once")
        by_index[i] = folder
    missing = sorted(set(range(count)) - set(by_index))
    if missing:
        raise ConfigError(f"shard(s) {', '.join(map(str, missing))} of {count} are missing (given: "
                          f"{', '.join(f'{i}: {by_index[i]}' for i in sorted(by_index))}): encode them with "
                          f"{shard_command('SHARD_DIR', missing[0], count)}, then merge all {count}")
    ordered = sorted(shards, key=lambda s: s[1]["part"]["shard_index"])
    stop = 0
    for folder, info in ordered:
        if info["part"]["start"] != stop or info["num_references"] != info["part"]["stop"] - info["part"]["start"]:
            raise ConfigError(f"the shard in {folder} holds rows {info['part']['start']}..{info['part']['stop']} "
                              f"({info['num_references']} references) where rows from {stop} were expected: it was "
                              f"written by another version of the sharding, or edited. Rebuild it with "
                              f"{shard_command(folder, info['part']['shard_index'], count)}")
        stop = info["part"]["stop"]
    if stop != ref["part"]["split_references"]:
        raise ConfigError(f"the {count} shards hold {stop} references, the split {ref['part']['split_references']}: "
                          f"rebuild them with the same gallery.num_shards")
    return ordered


def shard_folder(folder: Path) -> Path:
    """`folder`, refused unless it is a folder holding a gallery.json: what a shard job writes."""
    wrote = "give the folders the shard jobs wrote (evaluate.py gallery.num_shards=S gallery.shard_index=i " \
            "gallery.save=SHARD_DIR)"
    if not folder.exists():
        if any(c in str(folder) for c in "*?["):
            raise ConfigError(f"{folder} matched no folder (the shell passes a pattern that matches nothing as it "
                              f"is): check the pattern, and {wrote}")
        raise ConfigError(f"{folder}: no such folder; {wrote}")
    if not folder.is_dir():
        raise ConfigError(f"{folder} is a file, not a shard folder: {wrote}")
    if not (folder / INFO).is_file():
        raise ConfigError(f"{folder} holds no {INFO}, so no shard job wrote it: {wrote}")
    return folder


def check_moments(folder: Path, info: dict) -> None:
    """Refuse a shard whose gallery.json lacks the sums of its descriptors that merged_spread adds up."""
    moments = info.get("reference_moments")
    if not (isinstance(moments, dict) and all(isinstance(moments.get(k), list) and len(moments[k]) == info["dim"]
                                              for k in ("sum", "sum_sq"))):
        raise ConfigError(f"{folder / INFO} lacks reference_moments (the sums of the shard's descriptors, from "
                          f"which the merge computes the gallery's spread; {info['dim']} of each), or holds them in "
                          f"another form: it was edited or written by another version. {rebuild_shard(folder, info)}")


def check_index_files(folder: Path, info: dict) -> None:
    """Refuse a shard whose index files are not the ones its job wrote (gallery.json's `index_sha256`): a file
    copied from another shard of the same row count would merge, and its rows would stand for other references."""
    rebuild = rebuild_shard(folder, info)
    recorded = info.get("index_sha256")
    names = [f.name for f in index_files(folder / INDEX)]
    if not (isinstance(recorded, dict) and INDEX in recorded and set(recorded) <= set(names)):
        raise ConfigError(f"the shard in {folder}: {folder / INFO} records no digest of its index files "
                          f"(index_sha256): it was written by an earlier geoloc or edited. {rebuild}")
    for name, digest in recorded.items():
        path = folder / name
        if not path.is_file():
            raise ConfigError(f"the shard in {folder}: its index file {path} is missing. {rebuild}")
        if file_sha256(path) != digest:
            raise ConfigError(f"the shard in {folder}: its index file {path} is not the one its shard job wrote (its "
                              f"sha256 differs from the one {folder / INFO} records): it was copied from another "
                              f"shard or edited. {rebuild}")


def shard_index(folder: Path, info: dict) -> GalleryIndex:
    """The index of the shard in `folder`, loaded whole (it is merged into another), or a ConfigError naming the
    shard and the way to write it again."""
    try:
        return GalleryIndex.load(folder / INDEX, mmap=False)
    except (FileNotFoundError, ValueError) as err:
        raise ConfigError(f"the shard in {folder}: {err}. {rebuild_shard(folder, info)}") from None


def check_out(out: Path, folders: list[Path]) -> None:
    """Refuse an `out` that is one of the shard folders, lies inside one or holds one (paths resolved): writing the
    merged gallery there would replace or remove a shard, whose block would have to be encoded again."""
    target = out.resolve()
    for folder in folders:
        shard = folder.resolve()
        where = ("is the shard folder" if target == shard else "is inside the shard folder" if shard in target.parents
                 else "holds the shard folder" if target in shard.parents else None)
        if where:
            raise ConfigError(f"out={out} {where} {folder}: writing the merged gallery there would replace or remove "
                              "the shard, whose block would have to be encoded again. Choose an out= folder outside "
                              "the shards")


def merged_spread(shards: list[tuple[Path, dict]]) -> float:
    """descriptor_spread of all references (sum over dims of the per-dim sample std) from the shards' moments."""
    n = sum(info["num_references"] for _, info in shards)
    dims = range(shards[0][1]["dim"])
    total = [math.fsum(info["reference_moments"]["sum"][d] for _, info in shards) for d in dims]
    total_sq = [math.fsum(info["reference_moments"]["sum_sq"][d] for _, info in shards) for d in dims]
    return float(sum(math.sqrt(max(0.0, (sq - s * s / n) / max(1, n - 1))) for s, sq in zip(total, total_sq)))


def merge_shards(folders: list[str | Path], out: str | Path, overwrite: bool = False) -> tuple[dict, dict]:
    """Join the shard folders into one gallery folder `out`; returns its gallery.json and calibration.json records
    (confidence.across_jobs: the refiner's confidence as shard 0 holds it, the top-1 one uncalibrated)."""
    check_out(Path(out), [Path(f) for f in folders])
    shards = read_shards([Path(f) for f in folders])
    calibration = across_jobs(read_calibration(shards[0][0]))
    queries = {(folder / "queries.jsonl").read_bytes() for folder, _ in shards}
    if len(queries) != 1:
        raise ConfigError(f"the shards' queries.jsonl differ ({', '.join(str(f) for f, _ in shards)}): they were "
                          "written from other query lists of the split; rebuild the shards from one split")
    index = shard_index(*shards[0])  # the one that grows
    for folder, info in shards[1:]:  # one shard at a time in memory besides the merged index
        index.merge(shard_index(folder, info))
    info = {k: v for k, v in shards[0][1].items() if k not in ("part", "reference_moments", "reference_spread")}

    def fill(tmp: Path) -> dict:
        index.save(tmp / INDEX)
        paths = []
        with open(tmp / "references.jsonl", "wb") as out_file:
            for folder, _ in shards:
                with open(folder / "references.jsonl", "rb") as part:
                    shutil.copyfileobj(part, out_file)
                paths += [json.loads(line)["path"] for line in (folder / "references.jsonl").read_text().splitlines()
                          if line.strip()]
        if reference_paths_sha256(paths) != info["references_sha256"]:
            raise ConfigError(f"the shards' references.jsonl, joined in shard order, do not list the split's "
                              f"references (references_sha256 differs): a shard was edited or written by another "
                              f"version. Rebuild the shards ({', '.join(str(f) for f, _ in shards)})")
        (tmp / "queries.jsonl").write_bytes(next(iter(queries)))
        write_calibration(tmp, calibration)
        return {**info, "num_references": len(index), "reference_spread": merged_spread(shards),
                "merged_from": [str(f.resolve()) for f, _ in shards]}

    return write_gallery_folder(out, fill, overwrite), calibration
