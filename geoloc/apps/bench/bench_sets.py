"""The test sets `geoloc bench` knows: each as evaluate.py's overrides, on the released root the user gives
(`cvusa=/data/CVUSA`) or, without one, on its embedded synthetic world."""

from __future__ import annotations

from dataclasses import dataclass

from geoloc.config import ConfigError

ROOT_KEYS = ("cvusa", "cvact", "vigor", "u1652")  # the key=value arguments that give a released root
SYNTHETIC_CVACT = dict(preset="small", train=0, val=300, seed=0)  # the embedded CVACT world (no reader renders one)


@dataclass(frozen=True)
class TestSet:
    """One test set: `dataset` the evaluate.py overrides naming its data (without a root), `root_key` the argument
    giving its released root; `panorama`: its queries are panoramas, so the FoV / heading protocols apply (photo
    queries are scored at their own view alone). `published`: its key in published.yaml (default: `name`);
    `released_only`: scored on a released root alone (VIGOR's original labels: the embedded world has one label
    set)."""

    name: str
    dataset: tuple[str, ...]
    root_key: str
    panorama: bool = True
    published: str | None = None
    released_only: bool = False

    @property
    def published_as(self) -> str:
        return self.published or self.name


TEST_SETS = {t.name: t for t in (
    TestSet("cvusa", ("dataset=cvusa", "dataset.split=val"), "cvusa"),
    TestSet("cvact_val", ("dataset=cvact", "dataset.split=val"), "cvact"),
    TestSet("cvact_test", ("dataset=cvact", "dataset.split=test"), "cvact"),
    TestSet("vigor_same", ("dataset=vigor", "dataset.setting=same_area"), "vigor"),
    TestSet("vigor_cross", ("dataset=vigor", "dataset.setting=cross_area"), "vigor"),
    # VIGOR's other label set: the sets above read SliceMatch's corrected labels where the root holds them
    # (dataset.splits_dir=null), these the original ones, whose metres differ (docs/datasets.md, "Label sets")
    TestSet("vigor_same_original", ("dataset=vigor", "dataset.setting=same_area", "dataset.splits_dir=splits"),
            "vigor", published="vigor_same", released_only=True),
    TestSet("vigor_cross_original", ("dataset=vigor", "dataset.setting=cross_area", "dataset.splits_dir=splits"),
            "vigor", published="vigor_cross", released_only=True),
    TestSet("u1652_d2s", ("dataset=u1652", "dataset.direction=drone_to_satellite"), "u1652", panorama=False),
    TestSet("u1652_s2d", ("dataset=u1652", "dataset.direction=satellite_to_drone"), "u1652", panorama=False),
)}


def test_set(name: str) -> TestSet:
    if name not in TEST_SETS:
        raise ConfigError(f"sets: unknown test set {name!r}; geoloc bench knows {list(TEST_SETS)}")
    return TEST_SETS[name]


def data_overrides(test: TestSet, roots: dict[str, str | None]) -> tuple[list[str], bool]:
    """(evaluate.py's overrides of `test`, whether they read its embedded synthetic world). The synthetic CVUSA is
    the `synthetic` reader (CVUSA's layout); the synthetic CVACT is rendered here into $GEOLOC_CACHE (its val and
    test are one set: the renderer writes valSetAll as valSet); VIGOR and University-1652 render their own with no
    root."""
    root = roots.get(test.root_key)
    if root:
        return [*test.dataset, f"dataset.root={root}"], False
    if test.name == "cvusa":
        return ["dataset=synthetic", "dataset.split=val"], True
    if test.root_key == "cvact":
        return [*test.dataset, f"dataset.root={synthetic_cvact_root()}"], True
    return [*test.dataset, "dataset.root=null"], True


def synthetic_cvact_root() -> str:
    from geoloc.synthetic import default_cache, ensure_dataset

    name = "cvact-{preset}-{train}-{val}-seed{seed}".format(**SYNTHETIC_CVACT)
    return str(ensure_dataset("cvact", default_cache() / name, workers=1, **SYNTHETIC_CVACT))
