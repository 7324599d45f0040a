"""The four tables and the figures come out of one command on a tiny dataset."""

import json

import pytest
import torch
from test_dynamic_readers import write_tiny_dynamic
from test_mmdip_pipeline import TINY_MMDIP

from geoloc.tasks.mmdip import tables


@pytest.mark.slow
def test_tables_one_to_four_and_figures(tmp_path):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        root = write_tiny_dynamic(tmp_path / "dyn", n_train=3, n_val=3)
        out = tmp_path / "tables"
        overrides = [o for o in TINY_MMDIP if o != "task=mmdip"]
        tables.main(["--out", str(out), f"dataset.root={root}", "task.segmentation.unet_num_downs=3",
                     "task.segmentation.unet_ngf=8", "task.segmentation.fcn_width=8", *overrides])
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
