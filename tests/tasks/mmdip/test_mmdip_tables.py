"""The four tables and the figures come out of one command on a tiny dataset."""

import json

import pytest
import torch
from geoloc.apps import mmdip_tables
from geoloc.apps.mmdip_tables import tables

from helpers.dynamic_data import TINY_MMDIP, write_tiny_dynamic


@pytest.mark.slow
def test_tables_one_to_four_and_figures(tmp_path):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        root = write_tiny_dynamic(tmp_path / "dyn", n_train=3, n_val=3)
        out = tmp_path / "tables"
        overrides = [o for o in TINY_MMDIP if o != "task=mmdip"]
        mmdip_tables.main(["--out", str(out), f"dataset.root={root}", "+task.segmentation.unet.num_downs=3",
                           "+task.segmentation.unet.ngf=8", "+task.segmentation.fcn.width=8", *overrides])
    finally:
        torch.set_num_threads(threads)
    for n in (1, 2, 3, 4):
        assert (out / f"table_{n}.md").read_text().startswith(f"### Table {'I' * n if n < 4 else 'IV'}")
    t1 = json.loads((out / "table_1.json").read_text())
    assert set(t1) == {"erfnet", "fcn", "unet"} and t1["erfnet"]["params"] == 2063476
    t2 = json.loads((out / "table_2.json").read_text())
    assert set(t2) == {"pix2pix", "mgan", "ssggnet", "ssggnet_sm"}
    t3 = json.loads((out / "table_3.json").read_text())
    assert t3["num_queries"] == 3 and "ssggnet-BoW+SPM" in t3 and "mgan-BoW" in t3
    t4 = json.loads((out / "table_4.json").read_text())
    assert list(t4) == ["L=0", "L=2", "L=4", "L=6"] and all(v["coding_ms"] > 0 for v in t4.values())
    for png in ("recall_curves.png", "qualitative_ssggnet.png", "qualitative_variants.png"):
        assert (out / png).stat().st_size > 0


def test_mgan_rows_say_it_reads_the_ground_truth_mask(tmp_path):
    scores = {"L1": 0.1, "L2": 0.01, "PSNR": 20.0, "SSIM": 0.5}
    tables.table_2({"pix2pix": scores, "mgan": scores}, tmp_path)
    md, data = (tmp_path / "table_2.md").read_text(), json.loads((tmp_path / "table_2.json").read_text())
    assert "| MGAN (oracle mask) |" in md and "ground-truth dynamic-object mask at test time" in md
    assert data["mgan"]["oracle_mask"] is True and "oracle_mask" not in data["pix2pix"]
    recall = {k: 0.5 for k in ("R@1", "R@5", "R@10", "R@1%")}
    metrics = {"num_queries": 6, **{p + k: v for p in ("", "BoW/", "SPM/", "dynamic-BoW/") for k, v in recall.items()}}
    tables.table_3({"mgan": metrics, "ssggnet": metrics}, tmp_path)
    md, data = (tmp_path / "table_3.md").read_text(), json.loads((tmp_path / "table_3.json").read_text())
    assert "| MGAN (oracle mask) + BoW |" in md and "ground-truth dynamic-object mask at test time" in md
    assert data["mgan-BoW"]["oracle_mask"] is True and "oracle_mask" not in data["ssggnet-BoW"]
    tables.table_2({"ssggnet": scores}, tmp_path)  # no oracle row, no oracle note
    assert "oracle" not in (tmp_path / "table_2.md").read_text()
