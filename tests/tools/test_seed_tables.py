"""tools/seed_tables.py: mean ± std over runs of the same markdown tables, checked against statistics by hand."""

from __future__ import annotations

import importlib.util
import statistics

import pytest

from conftest import REPO

spec = importlib.util.spec_from_file_location("seed_tables", REPO / "tools" / "seed_tables.py")
seed_tables = importlib.util.module_from_spec(spec)
spec.loader.exec_module(seed_tables)


def write(run, r1, l1, method="BoW"):
    run.mkdir()
    (run / "table_3.md").write_text(f"### Table III (retrieval)\n\n| method | R@1 | L1 |\n|---|---|---|\n"
                                    f"| {method} | {r1} | {l1} |\n| SPM | 0.5 | 0.1 |\n")
    return run


def test_each_number_is_the_mean_and_sample_std_of_the_runs(tmp_path):
    runs = [write(tmp_path / f"s{i}", r1, l1) for i, (r1, l1) in enumerate([(0.7, 0.03), (0.6, 0.05), (0.8, 0.04)])]
    text = seed_tables.seed_table([r / "table_3.md" for r in runs], digits=4)
    mean, std = statistics.fmean([0.7, 0.6, 0.8]), statistics.stdev([0.7, 0.6, 0.8])
    assert f"| BoW | {mean:.4f} ± {std:.4f} | 0.0400 ± 0.0100 |" in text
    assert "| SPM | 0.5000 ± 0.0000 | 0.1000 ± 0.0000 |" in text
    assert text.startswith("### Table III (retrieval)") and "over 3 runs: s0, s1, s2" in text


def test_runs_of_different_commands_are_refused(tmp_path):
    a, b = write(tmp_path / "a", 0.7, 0.03), write(tmp_path / "b", 0.6, 0.05, method="SPM only")
    with pytest.raises(ValueError, match="disagree on a text cell"):
        seed_tables.seed_table([a / "table_3.md", b / "table_3.md"], digits=4)
