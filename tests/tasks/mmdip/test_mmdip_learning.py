"""MMDIP's coding finds places where it should: on static maps whose layout differs between places, the spatial
pyramid (eq. 4) and the fused similarity (eq. 5) retrieve the place far above chance, where a coarser pyramid or
either cue alone falls short.

No network is trained. Query codes are built directly with the two failures the method meets at test time: a
dynamic object the segmentation mislabels (one rectangle of a query map relabelled to one class), and places that
look alike (twin places share most of their visual words). They are scored through the run's own path: the
composed config's `task.vpr`, `Coder.spm` and `retrieval_metrics`, so a broken alpha or broken level weights
anywhere on that path fail here.
"""

import numpy as np
import pytest
from geoloc.config import checked
from geoloc.tasks.mmdip.mmdip_config import MMDIPConfig, VPRConfig
from geoloc.tasks.mmdip.datasets import NUM_CLASSES
from geoloc.tasks.mmdip.retrieval import Coder, retrieval_metrics

from conftest import compose_train

SIZE, BLOCKS = 32, 4  # 4 x 4 blocks of 8 x 8 pixels: the cells of SPM level 2
PLACES = 100  # chance R@1 = 0.01
# where a run's task.vpr comes from: the embedded default, the paper experiment, and the schema's own defaults
RUN_CONFIGS = ["task=mmdip", "experiment=paper_mmdip", "schema defaults"]


def run_vpr_config(source: str) -> VPRConfig:
    if source == "schema defaults":
        return VPRConfig()
    return checked(compose_train([source]).task, MMDIPConfig, "task").vpr


def place_maps(rng, n: int, occluder: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(query maps, reference maps), n x SIZE x SIZE: a random static class (1..7) per block for each place; its
    query is the same map with one rectangle of sides in `occluder` relabelled to one class."""
    cell = SIZE // BLOCKS
    refs = np.kron(rng.integers(1, NUM_CLASSES, (n, BLOCKS, BLOCKS)), np.ones((1, cell, cell), np.int64))
    queries = refs.copy()
    for q in queries:
        h, w = rng.integers(occluder[0], occluder[1] + 1, 2)
        y, x = rng.integers(0, SIZE - h + 1), rng.integers(0, SIZE - w + 1)
        q[y : y + h, x : x + w] = rng.integers(1, NUM_CLASSES)
    return queries.astype(np.uint8), refs.astype(np.uint8)


def twin_bows(rng, n: int, words: int = 256, shared: int = 20, own: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """(query, reference) visual-word counts, n x words. Places 2k and 2k + 1 share `shared` words (the same
    facades); every image adds `own` words of its own that its place's other view does not repeat, and queries
    lose a fifth of the shared counts and gain the same three 'car' words. BoW alone cannot tell twins apart."""
    query, reference = np.zeros((n, words)), np.zeros((n, words))
    car = rng.choice(words, 3, replace=False)
    for pair in range(n // 2):
        common, counts = rng.choice(words, shared, replace=False), rng.integers(1, 6, shared)
        for p in (2 * pair, 2 * pair + 1):
            reference[p, common] += counts
            query[p, common] += rng.binomial(counts, 0.8)
            for codes in (query, reference):
                codes[p, rng.choice(words, own, replace=False)] += rng.integers(1, 4, own)
            query[p, car] += rng.integers(0, 3, 3)
    return query, reference


@pytest.mark.parametrize("source", RUN_CONFIGS)
def test_spm_finds_the_place_behind_a_mislabelled_dynamic_object(source):
    cfg = run_vpr_config(source)
    coder = Coder(cfg, NUM_CLASSES)
    query_maps, ref_maps = place_maps(np.random.default_rng(0), PLACES, occluder=(16, 20))
    no_bow = np.zeros((PLACES, 1))

    def spm_recall(levels):
        return retrieval_metrics(no_bow, coder.spm(query_maps, levels), no_bow, coder.spm(ref_maps, levels),
                                 cfg)[0]["SPM/R@1"]

    # the data needs layout: the object shifts the whole-image class histogram (level 0) to other places'
    assert spm_recall(0) <= 0.2
    # eq. 4 weighs the finer levels up, where the object spoils only a few cells. Equal level weights gave
    # R@1 0.56 here and reversed weights 0.16: both let the spoilt coarse histogram dominate.
    assert spm_recall(cfg.levels) >= 0.9


@pytest.mark.parametrize("source", RUN_CONFIGS)
def test_fused_bow_and_spm_beat_each_cue_alone(source):
    cfg = run_vpr_config(source)
    rng = np.random.default_rng(0)
    query_maps, ref_maps = place_maps(rng, PLACES, occluder=(18, 24))
    query_bow, ref_bow = twin_bows(rng, PLACES)
    coder = Coder(cfg, NUM_CLASSES)
    m, _ = retrieval_metrics(query_bow, coder.spm(query_maps, cfg.levels), ref_bow, coder.spm(ref_maps, cfg.levels),
                             cfg)
    # each cue alone falls short: BoW confuses twins (about half right), SPM confuses the larger objects
    assert m["BoW/R@1"] <= 0.65 and m["SPM/R@1"] <= 0.8
    # BoW narrows the search to the twins and the layout picks one: eq. 5 at alpha = 0.5 gets nearly all.
    # alpha 0 gives SPM's R@1 (0.64 here), alpha 1 BoW's (0.46).
    assert m["R@1"] >= 0.9
    assert m["R@1"] >= max(m["BoW/R@1"], m["SPM/R@1"]) + 0.15
