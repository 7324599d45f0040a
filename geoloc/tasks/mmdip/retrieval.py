"""MMDIP place recognition: code queries and references, fuse (eq. 5), score with the project's recall.

Query (a dynamic image): segmentation -> static map M (SPM) and, through the generator, the recovered static
image (ORB BoW). Reference (a static landmark image): its static image (BoW) and its segmentation (SPM; predicted
from the static image, or the ground-truth labels with vpr.gallery_seg=label where the reader has labels).
Which images are queries and references, and where the vocabulary comes from: protocol.py, per reader.
Vocabulary and reference codes are saved artefacts in `artefact_dir` and reused. References are reordered so
reference[i] is query i's place (the one-to-one relevance the scorer ranks by). The recovered query images are
also scored against their own static view (L1, L2, PSNR, SSIM: Table II's scores), which every reader has.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from geoloc.eval.image import image_scores_per_image
from geoloc.data.relevance import Relevance
from geoloc.eval.recall import recall_summary
from geoloc.eval.scoring import rank
from geoloc.tasks.mmdip.mmdip_config import VPRConfig
from geoloc.tasks.mmdip.protocol import FROM_TRAIN, PlaceProtocol, describe
from geoloc.vpr import Gallery, ORBExtractor, Vocabulary, fused_descriptors, spm_encode

IMAGE_KEYS = ("L1", "L2", "PSNR", "SSIM")


def to_uint8(images: torch.Tensor) -> np.ndarray:
    """B x 3 x H x W in [0, 1] -> B x H x W x 3 uint8."""
    return (images.clamp(0, 1) * 255).round().byte().permute(0, 2, 3, 1).cpu().numpy()


class Coder:
    """ORB + vocabulary + SPM, configured once."""

    def __init__(self, cfg: VPRConfig, num_classes: int):
        self.cfg, self.num_classes = cfg, num_classes
        self.orb = ORBExtractor(cfg.orb_features, cfg.orb_patch_size, cfg.orb_fast_threshold)
        self.vocab: Vocabulary | None = None

    def bow(self, images: np.ndarray) -> np.ndarray:
        return np.stack([self.vocab.encode(self.orb(img)) for img in images])

    def spm(self, segs: np.ndarray, levels: int) -> np.ndarray:
        return np.stack([spm_encode(s, self.num_classes, levels) for s in segs])

    def fit_vocabulary(self, images) -> Vocabulary:
        self.vocab = Vocabulary.fit([self.orb(img) for img in images], self.cfg.vocab_size, self.cfg.vocab_iters)
        return self.vocab


def _loader(dataset, batch_size: int, num_workers: int) -> DataLoader:
    return DataLoader(dataset, batch_size=batch_size, shuffle=False, num_workers=num_workers)


@torch.no_grad()
def _run_queries(task, loader, device) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict, dict, dict]:
    """Dynamic images -> (recovered static uint8, M maps, places, input images, per-query seconds per stage,
    mean image scores of the recovered images against the static views)."""
    recovered, segs, places, dynamic, static = [], [], [], [], []
    seconds = {"segmentation": 0.0, "translation": 0.0}
    score_sums: dict[str, float] = {}
    for batch in loader:
        dyn = batch["dynamic"].to(device)
        t0 = time.perf_counter()
        logits = task.seg(dyn)
        _sync(device)
        t1 = time.perf_counter()
        fake = task.recover(dyn, logits, batch["mask"].to(device))
        _sync(device)
        seconds["segmentation"] += t1 - t0
        seconds["translation"] += time.perf_counter() - t1
        scores = image_scores_per_image((fake.float().clamp(-1, 1) + 1) / 2, batch["static"].to(device))
        for k, v in scores.items():
            score_sums[k] = score_sums.get(k, 0.0) + float(v.sum())
        recovered.append(to_uint8((fake.float() + 1) / 2))
        segs.append(logits.argmax(1).byte().cpu().numpy())
        places.append(batch["place"].numpy())
        dynamic.append(to_uint8(batch["dynamic"]))
        static.append(to_uint8(batch["static"]))
    n = sum(len(p) for p in places)
    inputs = {"dynamic": np.concatenate(dynamic), "static": np.concatenate(static)}
    return (np.concatenate(recovered), np.concatenate(segs), np.concatenate(places), inputs,
            {k: v / n for k, v in seconds.items()}, {k: v / n for k, v in score_sums.items()})


@torch.no_grad()
def _run_references(task, loader, device, use_labels: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    images, segs, places = [], [], []
    for batch in loader:
        static = batch["static"]
        seg = batch["label"] if use_labels else task.seg(static.to(device)).argmax(1)
        images.append(to_uint8(static))
        segs.append(seg.byte().cpu().numpy())
        places.append(batch["place"].numpy())
    return np.concatenate(images), np.concatenate(segs), np.concatenate(places)


def _sync(device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def match_order(query_places: np.ndarray, ref_places: np.ndarray) -> np.ndarray:
    """Permutation of the references putting query i's place at row i, the other references after."""
    where = {int(p): i for i, p in enumerate(ref_places)}
    if len(where) != len(ref_places):
        raise ValueError("the gallery holds two references of one place")
    missing = sorted({int(p) for p in query_places} - where.keys())
    if missing:
        raise ValueError(f"queries of places {missing[:5]} have no reference in the gallery")
    if len(set(query_places.tolist())) != len(query_places):
        raise ValueError("several queries of one place: the one-to-one ranking needs one query per reference")
    head = [where[int(p)] for p in query_places]
    rest = sorted(set(range(len(ref_places))) - set(head))
    return np.array(head + rest, dtype=np.int64)


def recall(q_bow, q_spm, r_bow, r_spm, alpha: float, ks) -> tuple[dict, torch.Tensor]:
    """Recall of eq. 5's fused similarity, ranked by the scorer (geoloc.eval.scoring); references already in
    query order (query i's place is reference i). Returns (metrics, ranks)."""
    q = torch.from_numpy(fused_descriptors(q_bow, q_spm, alpha, "query"))
    r = torch.from_numpy(fused_descriptors(r_bow, r_spm, alpha, "reference"))
    ranks = rank(q, r, Relevance.one_to_one(len(q), len(r))).ranks
    return recall_summary(ranks, tuple(ks), len(r)), ranks


def retrieval_metrics(q_bow, q_spm, r_bow, r_spm, cfg: VPRConfig) -> tuple[dict, dict]:
    """The MMDIP recall (eq. 5 at cfg.alpha: R@K, R@1%) and each cue alone (BoW/R@K: alpha 1, SPM/R@K: alpha 0)
    of codes whose reference row i is query i's place. Returns (metrics, ranks per method)."""
    ks, metrics, ranks = tuple(cfg.ks), {}, {}
    metrics, ranks["BoW+SPM"] = recall(q_bow, q_spm, r_bow, r_spm, cfg.alpha, ks)
    for name, alpha in (("BoW", 1.0), ("SPM", 0.0)):
        m, ranks[name] = recall(q_bow, q_spm, r_bow, r_spm, alpha, ks)
        metrics.update({f"{name}/{k}": v for k, v in m.items()})
    return metrics, ranks


def _reusable(path: Path, meta: dict) -> bool:
    """An artefact is reused only when it was made with the same settings (and the same model)."""
    manifest = path.with_suffix(".json")
    if not (path.is_file() and manifest.is_file()):
        return False
    try:
        return json.loads(manifest.read_text()) == meta
    except ValueError:  # a cut manifest: the artefact is made again
        return False


def _reusable_in(folders, name: str, meta: dict, beside: str | None = None) -> Path | None:
    """The first `folder/name` made with `meta` (and with `folder/beside` present), or None."""
    for folder in folders:
        path = Path(folder) / name
        if _reusable(path, meta) and (beside is None or (Path(folder) / beside).is_file()):
            return path
    return None


def _mark(path: Path, meta: dict) -> None:
    path.with_suffix(".json").write_text(json.dumps(meta, indent=1) + "\n")


def model_id(ckpt: Path) -> str:
    """Identifies the weights a gallery was coded with: the checkpoint's path and modification time."""
    ckpt = Path(ckpt).resolve()
    return f"{ckpt}@{ckpt.stat().st_mtime_ns}"


def evaluate_retrieval(task, protocol: PlaceProtocol, cfg: VPRConfig, device, artefact_dir: Path, model: str,
                       batch_size: int = 8, num_workers: int = 0, extra_levels=(), log=print,
                       reuse_from=()) -> dict:
    """Fused retrieval under `protocol` (a reader's place_protocol); returns metrics, ranks and examples.

    `model` identifies the weights (model_id of the checkpoint): a saved gallery is reused only for the same
    weights and settings, the vocabulary for the same images and ORB / vocabulary settings. Artefacts are looked
    for in `artefact_dir`, then in the `reuse_from` folders (read only: a training run's vpr/ seen from an
    evaluation); whatever is made, and metrics_<split>.json, is written to `artefact_dir` alone.
    Keys: R@K / R@1% / num_queries (BoW + SPM at cfg.levels), BoW/R@K (recovered image only), SPM/R@K,
    dynamic-BoW/R@K (the raw dynamic query, no recovery), L{l}/R@K and L{l}/coding_ms for `extra_levels`,
    ms/<stage> per query, L1 / L2 / PSNR / SSIM and num_images (recovered queries against their static views),
    and two strings that say how the numbers were made: gallery_seg and vocabulary_source.
    """
    artefact_dir = Path(artefact_dir)
    artefact_dir.mkdir(parents=True, exist_ok=True)
    task.eval().to(device)
    log(f"place protocol: {describe(protocol)}")
    coder = Coder(cfg, task.num_classes)
    vocab_path = artefact_dir / "vocabulary.npz"
    vocab_meta = {"dataset": protocol.name, "root": str(protocol.root.resolve()),
                  "image_size": list(protocol.image_size), "vocabulary_source": protocol.vocabulary_source,
                  **{k: getattr(cfg, k) for k in ("vocab_size", "vocab_iters", "orb_features", "orb_patch_size",
                                                  "orb_fast_threshold")}}
    if protocol.vocabulary_source != FROM_TRAIN:
        vocab_meta["split"] = protocol.split  # the gallery's own images
    found = _reusable_in([artefact_dir, *reuse_from], vocab_path.name, vocab_meta)
    if found is not None:
        coder.vocab = Vocabulary.load(found)
        if found != vocab_path:
            log(f"vocabulary: {found} (read only)")
    else:
        images = protocol.vocabulary
        imgs = [to_uint8(images[i]["static"][None])[0] for i in range(len(images))]
        coder.fit_vocabulary(imgs).save(vocab_path)
        _mark(vocab_path, vocab_meta)
        log(f"vocabulary: {coder.vocab.size} words from {len(imgs)} static images of the "
            f"{protocol.vocabulary_source} -> {vocab_path}")

    gallery_seg = cfg.gallery_seg if protocol.has_labels else "predicted"
    if gallery_seg != cfg.gallery_seg:
        log(f"vpr.gallery_seg=label: dataset={protocol.name} has no segmentation labels, so the gallery's SPM "
            f"codes the predicted static segmentation of each reference image")
    stem = f"gallery_{protocol.split or 'all'}_{gallery_seg}"
    gallery_path, seg_path = artefact_dir / f"{stem}.npz", artefact_dir / f"{stem}_seg.npy"
    gallery_meta = {**vocab_meta, "split": protocol.split, "gallery_seg": gallery_seg, "levels": cfg.levels,
                    "model": model if gallery_seg == "predicted" else None}
    found = _reusable_in([artefact_dir, *reuse_from], gallery_path.name, gallery_meta, beside=seg_path.name)
    if found is not None:
        gallery, ref_segs = Gallery.load(found), np.load(found.parent / seg_path.name)
        if found != gallery_path:
            log(f"gallery: {found} (read only)")
    else:
        ref_imgs, ref_segs, ref_places = _run_references(
            task, _loader(protocol.references, batch_size, num_workers), device, gallery_seg == "label")
        gallery = Gallery(coder.bow(ref_imgs), coder.spm(ref_segs, cfg.levels), ref_places, cfg.levels)
        gallery.save(gallery_path)
        np.save(seg_path, ref_segs)
        _mark(gallery_path, gallery_meta)
        log(f"gallery: {len(ref_places)} references of split '{protocol.split}' -> {gallery_path}")
    rec, q_segs, q_places, q_inputs, seconds, image_scores = _run_queries(
        task, _loader(protocol.queries, batch_size, num_workers), device)
    t0 = time.perf_counter()
    q_bow = coder.bow(rec)
    t1 = time.perf_counter()
    q_spm = coder.spm(q_segs, cfg.levels)
    t2 = time.perf_counter()
    n = len(q_places)
    order = match_order(q_places, gallery.places)
    r_bow, r_spm, r_segs = gallery.bow[order], gallery.spm[order], ref_segs[order]

    ks = tuple(cfg.ks)
    t3 = time.perf_counter()
    metrics, ranks = retrieval_metrics(q_bow, q_spm, r_bow, r_spm, cfg)
    seconds["retrieval"] = (time.perf_counter() - t3) / n / 3  # three recalls of one size: fused, BoW, SPM
    seconds["bow_coding"], seconds["spm_coding"] = (t1 - t0) / n, (t2 - t1) / n
    metrics["num_queries"] = n
    m, ranks["dynamic-BoW"] = recall(coder.bow(q_inputs["dynamic"]), q_spm, r_bow, r_spm, 1.0, ks)
    metrics.update({f"dynamic-BoW/{k}": v for k, v in m.items()})
    for lvl in extra_levels:
        t0 = time.perf_counter()
        q_lvl = coder.spm(q_segs, lvl)
        ms = (time.perf_counter() - t0) / n * 1e3 + seconds["bow_coding"] * 1e3
        m, ranks[f"L{lvl}"] = recall(q_bow, q_lvl, r_bow, coder.spm(r_segs, lvl), cfg.alpha, ks)
        metrics.update({f"L{lvl}/{k}": v for k, v in m.items()})
        metrics[f"L{lvl}/coding_ms"] = ms
    metrics.update({f"ms/{k}": v * 1e3 for k, v in seconds.items()})
    metrics.update(image_scores)
    metrics["num_images"] = n
    metrics.update(gallery_seg=gallery_seg, vocabulary_source=protocol.vocabulary_source)
    (artefact_dir / f"metrics_{protocol.split or 'all'}.json").write_text(json.dumps(metrics, indent=2) + "\n")
    return {"metrics": metrics, "ranks": ranks,
            "examples": {**q_inputs, "recovered": rec, "seg": q_segs, "places": q_places}}


def print_recall(metrics: dict, title: str) -> None:
    """evaluate_retrieval's metrics: recall of the fused codes, each cue alone and the raw query; image scores."""
    print(f"\n{title} ({metrics['num_queries']} queries; vocabulary from the {metrics['vocabulary_source']}, "
          f"gallery SPM from the {metrics['gallery_seg']} segmentation)")
    rows = [("BoW+SPM", ""), ("BoW", "BoW/"), ("SPM", "SPM/"), ("dynamic image BoW", "dynamic-BoW/")]
    keys = [k for k in metrics if k.startswith("R@")]
    print("| method | " + " | ".join(keys) + " |\n|---|" + "---|" * len(keys))
    for name, prefix in rows:
        print(f"| {name} | " + " | ".join(f"{metrics[prefix + k]:.4f}" for k in keys) + " |")
    print("recovered queries against their static views: " + "  ".join(f"{k} {metrics[k]:.4g}" for k in IMAGE_KEYS))
