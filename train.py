"""Train a geoloc task. `python train.py` runs the embedded default (cross-view on synthetic data).

Examples: python train.py dataset=cvusa dataset.root=/data/CVUSA
          python train.py task=mmdip
          python train.py -m dataset.alignment=ipt,none   (an ablation sweep)
          torchrun --nproc_per_node=2 train.py trainer.device=cpu
"""

from geoloc.entry_points import train as main  # composes geoloc/conf/train.yaml with the arguments

if __name__ == "__main__":
    main()
