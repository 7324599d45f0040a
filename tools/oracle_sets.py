"""Is the positive distinguishable without training? Scores the test splits of the synthetic VIGOR and
University-1652 medium worlds with fixed, untrained similarities (docs/datasets.md, "Why the CPU recipe stays near
chance on them").

    PYTHONPATH=. python tools/oracle_sets.py

The 64 px inputs the CPU recipes see (VIGOR: the IPT of the horizon band, and for cross-area also its ground-plane
projection; University-1652: drone views as photos),
described by tools/oracle_heading.py's `pixels` and `randconv` descriptors and scored by geoloc's split_metrics.
"""

import torch

from geoloc.eval.retrieval_metrics import split_metrics
from geoloc.tasks.crossview.data_config import parse_dataset
from geoloc.tasks.crossview.datasets import build_eval

from oracle_heading import descriptors, random_features

SETTINGS = [("u1652", {"preset": "u1652_medium", "alignment": "none"}),
            ("vigor", {"preset": "vigor_medium", "alignment": "ipt"}),
            ("vigor", {"preset": "vigor_medium", "alignment": "ipt", "setting": "cross_area"}),
            ("vigor", {"preset": "vigor_medium", "alignment": "ground", "camera_height_m": 2.2,
                       "setting": "cross_area"})]


def main() -> None:
    conv = random_features()
    for name, keys in SETTINGS:
        data, reader = parse_dataset({"name": name, "aerial_size": 64, "pano_size": [32, 176], **keys})
        test = build_eval(data, reader, "test")
        queries = torch.stack([test.queries[i]["image"] for i in range(len(test.queries))])
        references = torch.stack([test.references[i]["image"] for i in range(len(test.references))])
        for kind in ("pixels", "randconv"):
            m = split_metrics(descriptors(queries, kind, conv), descriptors(references, kind, conv), test.split)
            shown = {k: round(100 * v, 2) for k, v in m.items() if k in ("R@1", "R@10", "AP", "hit_rate")}
            print(name, keys.get("setting", ""), keys["alignment"], kind, len(queries), len(references), shown,
                  flush=True)


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
