"""The MMDIP paper's tables and figures on one dataset: make_tables(cfg, out), run by one command
(geoloc/apps/mmdip_tables/command.py):

    python -m geoloc.apps.mmdip_tables --out DIR [--tables I II III IV] [hydra overrides ...]

  Table I    phase 1 for ERFNet, FCN and U-Net: per-class IoU, PA, MPA, MIoU, FWIoU, parameter counts
  Table II   phase 2 for pix2pix, MGAN, SSGGNet, SSGGNet-SM: L1, L2, PSNR, SSIM on the validation split.
             MGAN is given the ground-truth dynamic mask at test time, an oracle: its rows say "oracle mask".
  Table III  R@1/5/10/1% of each generator + BoW, of the raw dynamic image + BoW, of SPM alone and of the full
             SSGGNet BoW + SPM; recall curves (Fig. 4) in recall_curves.png
  Table IV   SSGGNet BoW + SPM at pyramid levels L = 0, 2, 4, 6: recall and per-query coding time
  Figures    qualitative_ssggnet.png (Fig. 2: dynamic | predicted static seg | recovered | ground truth) and
             qualitative_variants.png (Fig. 3: dynamic | pix2pix | MGAN | SSGGNet-SM | SSGGNet | ground truth)

Each table is written as DIR/table_<n>.md and DIR/table_<n>.json. Phase 2 of every variant starts from the
ERFNet phase-1 checkpoint, so Tables II and III compare generators on one segmentation network. Retrieval follows
the place protocol of the dataset's reader (readers.py). Table I runs each segmenter with its own keys from
task.segmentation.<segmenter> (e.g. task.segmentation.unet.num_downs). SRMGAN, a row of the paper's Tables II-III,
is not implemented (docs/mmdip.md says why).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from geoloc.config import to_yaml  # noqa: E402
from geoloc.tasks.mmdip.datasets import STATIC_CLASSES  # noqa: E402
from geoloc.synthetic.classes import colorize  # noqa: E402
from geoloc.eval.plots import grid, save_png  # noqa: E402
from geoloc.tasks.mmdip.pipeline import parse, run_phase1, run_phase2  # noqa: E402
from geoloc.tasks.mmdip.readers import build_reader  # noqa: E402
from geoloc.tasks.mmdip.retrieval import evaluate_retrieval, model_id  # noqa: E402

SEGMENTERS = {"erfnet": "ERFNet", "fcn": "FCN-8s (small)", "unet": "U-Net"}
# MGAN reads the ground-truth dynamic-object mask at test time (networks.generator_input): an oracle input no
# other row gets, so every table and figure that shows it says so.
VARIANTS = {"pix2pix": "pix2pix", "mgan": "MGAN (oracle mask)", "ssggnet_sm": "SSGGNet-SM", "ssggnet": "SSGGNet"}
ORACLE_VARIANTS = ("mgan",)
ORACLE_NOTE = ("MGAN (oracle mask) is given the ground-truth dynamic-object mask at test time; the other rows see "
               "the dynamic image only.")
LEVELS = (0, 2, 4, 6)
RECALL_KEYS = ("R@1", "R@5", "R@10", "R@1%")


def oracle_note(variants) -> str:
    return ORACLE_NOTE if set(variants) & set(ORACLE_VARIANTS) else ""


def write_table(out: Path, name: str, title: str, header: list[str], rows: list[list], data,
                note: str = "") -> str:
    fmt = lambda v: f"{v:.4f}" if isinstance(v, float) else str(v)
    lines = [f"### {title}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]
    lines += ["", note] if note else []
    text = "\n".join(lines) + "\n"
    (out / f"{name}.md").write_text(text)
    (out / f"{name}.json").write_text(json.dumps(data, indent=2) + "\n")
    print("\n" + text)
    return text


def table_1(results: dict, out: Path) -> None:
    header = ["model", "params (M)", *STATIC_CLASSES, "PA", "MPA", "MIoU", "FWIoU"]
    rows = []
    for name, r in results.items():
        ious = [r["metrics"].get(f"IoU_{c}", float("nan")) for c in range(len(STATIC_CLASSES))]
        rows.append([SEGMENTERS[name], f"{r['params'] / 1e6:.2f}", *ious,
                     *(r["metrics"][k] for k in ("PA", "MPA", "MIoU", "FWIoU"))])
    write_table(out, "table_1", "Table I: static semantic segmentation (validation split)", header, rows, results)


def table_2(results: dict, out: Path) -> None:
    rows = [[VARIANTS[v], *(r[k] for k in ("L1", "L2", "PSNR", "SSIM"))] for v, r in results.items()]
    results = {v: {**r, "oracle_mask": True} if v in ORACLE_VARIANTS else r for v, r in results.items()}
    write_table(out, "table_2", "Table II: static image recovery (validation split; L2 = mean squared error)",
                ["generator", "L1", "L2", "PSNR (dB)", "SSIM"], rows, results, oracle_note(results))


def table_3(vpr: dict, out: Path) -> None:
    rows, data = [], {}
    for v, m in vpr.items():
        recall = {k: m[f"BoW/{k}"] for k in RECALL_KEYS}
        rows.append([f"{VARIANTS[v]} + BoW", *recall.values()])
        data[f"{v}-BoW"] = {**recall, "oracle_mask": True} if v in ORACLE_VARIANTS else recall
    ref = vpr["ssggnet"]
    for key, label, prefix in (("dynamic-BoW", "dynamic image + BoW (no recovery)", "dynamic-BoW/"),
                               ("SPM", "static segmentation SPM alone", "SPM/"),
                               ("ssggnet-BoW+SPM", "SSGGNet + BoW + SPM (MMDIP)", "")):
        data[key] = {k: ref[prefix + k] for k in RECALL_KEYS}
        rows.append([label, *data[key].values()])
    data["num_queries"] = ref["num_queries"]
    write_table(out, "table_3", f"Table III: place recognition, {ref['num_queries']} queries (L = 2, alpha = 0.5)",
                ["method", *RECALL_KEYS], rows, data, oracle_note(vpr))


def table_4(metrics: dict, out: Path) -> None:
    data = {f"L={l}": {**{k: metrics[f"L{l}/{k}"] for k in RECALL_KEYS},
                       "coding_ms": metrics[f"L{l}/coding_ms"]} for l in LEVELS}
    rows = [[name, *d.values()] for name, d in data.items()]
    write_table(out, "table_4", "Table IV: SPM pyramid levels (SSGGNet + BoW + SPM; coding = BoW + SPM per query)",
                ["levels", *RECALL_KEYS, "coding ms/query"], rows, data)


def recall_curves(ranks: dict[str, dict], out: Path) -> None:
    fig, ax = plt.subplots(figsize=(5, 3.5), dpi=120)
    for label, r in ranks.items():
        r = r.numpy()
        kmax = min(25, len(r))
        ax.plot(range(1, kmax + 1), [100 * np.mean(r < k) for k in range(1, kmax + 1)], marker=".", label=label)
    ax.set_xlabel("K")
    ax.set_ylabel("recall@K (%)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "recall_curves.png")
    plt.close(fig)


def qualitative(examples: dict[str, dict], out: Path, n: int = 4) -> None:
    ss = examples["ssggnet"]
    rows = [[ss["dynamic"][i], colorize(ss["seg"][i]), ss["recovered"][i], ss["static"][i]] for i in range(n)]
    save_png(out / "qualitative_ssggnet.png", grid(rows))
    order = [v for v in ("pix2pix", "mgan", "ssggnet_sm", "ssggnet") if v in examples]
    rows = [[ss["dynamic"][i], *(examples[v]["recovered"][i] for v in order), ss["static"][i]] for i in range(n)]
    save_png(out / "qualitative_variants.png", grid(rows))


def make_tables(cfg, out: Path, tables=("I", "II", "III", "IV")) -> dict:
    task_cfg, data_cfg, trainer_cfg = parse(cfg)
    out.mkdir(parents=True, exist_ok=True)
    yaml = to_yaml(cfg)
    (out / "config.yaml").write_text(yaml)
    reader = build_reader(data_cfg)
    fractions = reader.class_fractions()
    protocol = reader.place_protocol(data_cfg.split)
    train_set = reader.split("train", train=True, seed=trainer_cfg.seed)
    val_set = reader.split("val")
    summary = {}

    seg_models = list(SEGMENTERS) if "I" in tables else ["erfnet"]
    seg_results = {}
    for name in seg_models:
        c = dataclasses.replace(task_cfg, segmentation=dataclasses.replace(task_cfg.segmentation, model=name))
        task, best = run_phase1(c, data_cfg, trainer_cfg, train_set, val_set, fractions, out / f"phase1_{name}", yaml)
        seg_results[name] = {"metrics": best, "params": sum(p.numel() for p in task.seg.parameters())}
    if "I" in tables:
        table_1(seg_results, out)
        summary["I"] = seg_results
    if not {"II", "III", "IV"} & set(tables):
        return summary

    variants = list(VARIANTS) if {"II", "III"} & set(tables) else ["ssggnet"]
    gen_results, vpr, ranks, examples = {}, {}, {}, {}
    for v in variants:
        c = dataclasses.replace(task_cfg, translation=dataclasses.replace(task_cfg.translation, variant=v))
        task, best, device = run_phase2(c, data_cfg, trainer_cfg, train_set, val_set, fractions,
                                        out / f"phase2_{v}", yaml, out / "phase1_erfnet" / "best.pt")
        gen_results[v] = {k: best[k] for k in ("L1", "L2", "PSNR", "SSIM")}
        art = out / f"vpr_{v}"
        art.mkdir(exist_ok=True)
        if v != variants[0]:  # one vocabulary for every generator
            for name in ("vocabulary.npz", "vocabulary.json"):
                shutil.copy(out / f"vpr_{variants[0]}" / name, art / name)
        res = evaluate_retrieval(task, protocol, task_cfg.vpr, device, art, model_id(out / f"phase2_{v}" / "best.pt"),
                                 data_cfg.val_batch_size, extra_levels=LEVELS if v == "ssggnet" else ())
        vpr[v], examples[v] = res["metrics"], res["examples"]
        ranks[f"{VARIANTS[v]} + BoW"] = res["ranks"]["BoW"]
        if v == "ssggnet":
            ranks["dynamic image + BoW"] = res["ranks"]["dynamic-BoW"]
            ranks["SPM alone"] = res["ranks"]["SPM"]
            ranks["SSGGNet + BoW + SPM"] = res["ranks"]["BoW+SPM"]
    if "II" in tables:
        table_2(gen_results, out)
        summary["II"] = gen_results
    if "III" in tables:
        table_3(vpr, out)
        recall_curves(ranks, out)
        summary["III"] = vpr
    if "IV" in tables:
        table_4(vpr["ssggnet"], out)
        summary["IV"] = {k: v for k, v in vpr["ssggnet"].items() if k.startswith("L")}
    qualitative(examples, out, n=min(4, len(examples["ssggnet"]["dynamic"])))
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
    return summary
