"""Write a checkpoint's trunk as weights geoloc can ship (docs/backbones.md, "Weights shipped with geoloc").

    python tools/export_trunk.py RUN/last.pt OUT_DIR NAME --recipe "python train.py ..." [--branch query]
        [--data-marker DATA_ROOT/geoloc_synthetic.json] [--note TEXT]

Writes OUT_DIR/NAME.pt, the state dict of the branch's trunk (`features.*`, as a torchvision VGG16 file holds
them), and OUT_DIR/NAME.json, its card: the backbone section it fits, the recipe given, the run's seed, epochs and
pairs, the data it saw (the checkpoint's dataset section, and the synthetic renderer's marker where given), the
environment it was trained in and the file's sha256. A model with one shared trunk gives it whichever branch is
named; an unshared one needs --branch, since its two trunks differ. Nothing existing is overwritten.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

from geoloc.engine import checkpoint
from geoloc.tasks.crossview.crossview_run import stored_config

DATA_KEYS = ("name", "preset", "train_size", "val_size", "seed", "aerial_size", "pano_size")


def trunk_state(task: dict, branch: str) -> dict:
    """The `features.*` tensors of model.<branch>.trunk; refused for an unshared model's branch left unnamed."""
    prefix = f"model.{branch}.trunk."
    state = {k[len(prefix):]: v.clone() for k, v in task.items() if k.startswith(prefix)}
    if not state:
        raise SystemExit(f"the checkpoint has no model.{branch}.trunk tensors")
    return state


def card(ckpt: dict, name: str, digest: str, recipe: str, marker: dict | None, note: str) -> dict:
    cfg = OmegaConf.to_container(stored_config(ckpt), resolve=True)
    backbone = {k: cfg["backbone"][k] for k in ("name", "width", "batchnorm") if k in cfg["backbone"]}
    data = {k: cfg["dataset"].get(k) for k in DATA_KEYS}
    if marker is not None:
        data["renderer"] = {k: marker.get(k) for k in ("generator", "version", "layout", "preset", "seed")}
    epochs = int(ckpt["epoch"]) + 1
    return {"name": name, "file": f"{name}.pt", "sha256": digest, "backbone": backbone, "recipe": recipe,
            "seed": cfg.get("seed"), "epochs": epochs,
            "pairs": int(ckpt["global_step"]) * int(cfg["dataset"]["batch_size"]),
            "shared_trunk": bool(cfg["model"].get("shared", False)), "data": data,
            "environment": ckpt.get("environment"), "note": note}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ckpt")
    parser.add_argument("out_dir")
    parser.add_argument("name")
    parser.add_argument("--recipe", required=True, help="the command that trained the checkpoint")
    parser.add_argument("--branch", choices=("query", "reference"), default=None)
    parser.add_argument("--data-marker", default=None, help="the synthetic data root's geoloc_synthetic.json")
    parser.add_argument("--note", default="")
    args = parser.parse_args(argv)
    out = Path(args.out_dir)
    files = [out / f"{args.name}.pt", out / f"{args.name}.json"]
    taken = [str(f) for f in files if f.exists()]
    if taken:
        raise SystemExit(f"{', '.join(taken)} exist: choose another name or folder (nothing is overwritten)")
    ckpt = checkpoint.load(args.ckpt)
    query, reference = trunk_state(ckpt["task"], "query"), trunk_state(ckpt["task"], "reference")
    shared = query.keys() == reference.keys() and all(torch.equal(query[k], reference[k]) for k in query)
    if not shared and args.branch is None:
        raise SystemExit("the model's two trunks differ (model.shared=false): name the one to write with --branch")
    state = reference if args.branch == "reference" else query
    out.mkdir(parents=True, exist_ok=True)
    torch.save(state, files[0])
    digest = hashlib.sha256(files[0].read_bytes()).hexdigest()
    marker = json.loads(Path(args.data_marker).read_text()) if args.data_marker else None
    files[1].write_text(json.dumps(card(ckpt, args.name, digest, args.recipe, marker, args.note), indent=2) + "\n")
    print(f"{files[0]} ({files[0].stat().st_size} bytes, sha256 {digest[:16]}...) and {files[1]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
