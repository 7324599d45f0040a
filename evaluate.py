"""Evaluate a checkpoint: python evaluate.py ckpt=outputs/.../best.pt [dataset=cvusa dataset.root=DIR
dataset.split=val] metrics_out=metrics.json. Model and transforms are rebuilt from the checkpoint's config."""

from geoloc.entry_points import evaluate as main  # composes geoloc/conf/evaluate.yaml with the arguments

if __name__ == "__main__":
    main()
