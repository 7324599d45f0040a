"""Tiny dynamic-scene datasets on disk and the MMDIP evaluation call, shared by the MMDIP tests."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
from geoloc.tasks import mmdip


def write_tiny_dynamic(root: Path, n_train: int = 4, n_val: int = 3, size=(64, 64), seed: int = 0) -> Path:
    """A `dynamic` layout folder (docs/dynamic_layout.md): one reference and one query per place."""
    rng = np.random.default_rng(seed)
    for d in ("splits", "rgb_dynamic", "rgb_static", "label_static", "label_dynamic", "mask_dynamic"):
        (root / d).mkdir(parents=True, exist_ok=True)
    (root / "geoloc_synthetic.json").write_text(json.dumps({"layout": "dynamic", "seed": seed}))
    header = "sample,place,role,x,y,yaw,sun_azimuth,sun_elevation\n"
    rows = {"train": [header], "val": [header]}
    counts = np.zeros(8)
    sample = 0
    for place in range(n_train + n_val):
        split = "train" if place < n_train else "val"
        lab, rgb = _scene(rng, size)
        for role in ("reference", "query"):
            shift = 0 if role == "reference" else int(rng.integers(-2, 3))
            lab_v, rgb_v = np.roll(lab, shift, axis=1), np.roll(rgb, shift, axis=1)
            dyn, mask = rgb_v.copy(), np.zeros(size, np.uint8)
            for _ in range(2):  # cars on the road
                y, x = rng.integers(3 * size[0] // 4 - 4, size[0] - 8), rng.integers(0, size[1] - 12)
                dyn[y : y + 8, x : x + 12] = (0, 0, 142)
                mask[y : y + 8, x : x + 12] = 255
            name = f"{sample:07d}"
            cv2.imwrite(str(root / f"rgb_static/{name}.png"), cv2.cvtColor(rgb_v, cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(root / f"rgb_dynamic/{name}.png"), cv2.cvtColor(dyn, cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(root / f"label_static/{name}.png"), lab_v)
            cv2.imwrite(str(root / f"label_dynamic/{name}.png"), np.where(mask > 0, 8, lab_v).astype(np.uint8))
            cv2.imwrite(str(root / f"mask_dynamic/{name}.png"), mask)
            rows[split].append(f"{name},{place},{role},0,0,0,0,45\n")
            if split == "train":
                counts += np.bincount(lab_v.ravel(), minlength=8)
            sample += 1
    for split, lines in rows.items():
        (root / f"splits/{split}.csv").write_text("".join(lines))
    (root / "class_fractions.json").write_text(json.dumps({"classes": [str(i) for i in range(8)],
                                                            "fractions": (counts / counts.sum()).tolist()}))
    return root


def write_four_panel(path: Path, h=16, w=24, seed=0, bad_tag=None):
    rng = np.random.default_rng(seed)
    dyn, sta = rng.integers(0, 255, (h, w, 3), np.uint8), rng.integers(0, 255, (h, w, 3), np.uint8)
    sta_tags = rng.integers(0, 13, (h, w)).astype(np.uint8)
    sta_tags[sta_tags == 4] = 7  # the static panel has no dynamic tags
    sta_tags[sta_tags == 10] = 8
    dyn_tags = sta_tags.copy()
    dyn_tags[:4, :4], dyn_tags[-3:, -5:] = 10, 4  # a vehicle and a pedestrian
    if bad_tag is not None:
        sta_tags[0, 0] = bad_tag
    rgb_tags = lambda t: np.repeat(t[..., None], 3, axis=2)
    img = np.concatenate([dyn, rgb_tags(dyn_tags), sta, rgb_tags(sta_tags)], axis=1)
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    return dyn, sta, dyn_tags, sta_tags


def evaluate(cfg, ckpt, metrics_out=None) -> dict:
    """mmdip.evaluate(cfg) with cfg.ckpt set, its metrics written to `metrics_out` as geoloc.launch.run.evaluate
    writes them (without the launcher's run-dir claim: `cfg` is a training config here)."""
    from geoloc.launch.run import write_metrics
    from omegaconf import open_dict

    with open_dict(cfg):
        cfg.ckpt = str(ckpt)
    metrics = mmdip.evaluate(cfg)
    if metrics_out:
        write_metrics(Path(metrics_out), metrics, overwrite=False)
    return metrics


TINY_MMDIP = [
    "task=mmdip", "dataset.image_size=[64,64]", "dataset.val_batch_size=4",
    "task.segmentation.epochs=1", "task.segmentation.batch_size=4",
    "task.translation.epochs=1", "task.translation.batch_size=4", "task.translation.num_downs=4",
    "task.translation.ngf=8", "task.translation.ndf=8", "task.translation.d_layers=2",
    "task.translation.perceptual_layers=[relu1_2]", "task.vpr.vocab_size=16", "task.vpr.orb_patch_size=11",
    "task.vpr.orb_fast_threshold=5", "trainer.num_workers=0", "trainer.progress=false", "trainer.device=cpu",
]


def _scene(rng, size):
    """A static label map and a textured RGB rendering of it."""
    h, w = size
    lab = np.zeros((h, w), np.uint8)
    lab[h // 3 :, :] = 1  # buildings
    lab[h // 2 :, : w // 4] = 7  # vegetation
    lab[h // 2 : h // 2 + 2, w // 4 : w // 2] = 2  # fence
    lab[2 * h // 3 :, :] = 6  # sidewalk
    lab[3 * h // 4 :, :] = 5  # road
    lab[7 * h // 8, ::4] = 4  # road lines
    lab[h // 3 : h // 2, rng.integers(w // 2, w - 4) :] = 3  # others, place-specific
    rgb = PALETTE[lab].astype(np.int16)
    for _ in range(12):  # place-specific windows: corners for ORB
        y, x = rng.integers(h // 3, 2 * h // 3 - 4), rng.integers(0, w - 6)
        rgb[y : y + 4, x : x + 6] = rng.integers(0, 255, 3)
    return lab, np.clip(rgb + rng.integers(-8, 8, rgb.shape), 0, 255).astype(np.uint8)


PALETTE = np.array([(0, 0, 0), (70, 70, 70), (190, 153, 153), (220, 220, 0), (157, 234, 50), (128, 64, 128),
                    (244, 35, 232), (107, 142, 35)], np.uint8)
