"""`geoloc gallery merge`: its keys are geoloc/conf/gallery_folders.yaml over FolderKeys, composed in Hydra's grammar as
the other verbs compose theirs; a bad one is refused in one line before any shard is read."""

from __future__ import annotations

import pytest

from geoloc import cli, gallery


@pytest.fixture
def merged(monkeypatch):
    calls = []
    monkeypatch.setattr(gallery, "merge_shards", lambda folders, out, overwrite: calls.append(
        (folders, out, overwrite)) or ({"num_references": 3, "kind": "flat"}, {"calibrated": True}))
    return calls


def test_the_shard_folders_are_the_arguments_without_an_equals_sign_and_the_keys_take_hydras_grammar(merged, capsys):
    assert cli.main(["gallery", "merge", "s0", "s1", "out='merged,1'"]) == 0  # quoted: a comma kept in the path
    assert cli.main(["gallery", "merge", "s0", "out=m", "overwrite=true"]) == 0
    assert merged == [(["s0", "s1"], "merged,1", False), (["s0"], "m", True)]
    assert "merged,1: 3 references (flat) from 2 shards" in capsys.readouterr().out


@pytest.mark.parametrize("keys, says", [
    (["out=m", "overwrit=true"], "bad 'gallery merge' config: Could not override 'overwrit'."),
    (["out=m", "+overwrit=true"], "bad 'gallery merge' config: Key 'overwrit' not in 'FolderKeys'"),
    (["out=m", "overwrite=maybe"], "bad 'gallery merge' config: Value 'maybe' is not a valid bool (type str)"),
    ([], "bad 'gallery merge' config: Structured config of type `FolderKeys` has missing mandatory value: out"),
])
def test_a_bad_key_is_one_line_naming_it_and_exit_2_before_any_shard_is_read(merged, capsys, keys, says):
    assert cli.main(["gallery", "merge", "s0", *keys]) == 2
    assert capsys.readouterr().err.splitlines()[0] == f"geoloc gallery: {says}"
    assert merged == []
