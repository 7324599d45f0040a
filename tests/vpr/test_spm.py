"""SPM coding of a segmentation map (MMDIP eq. 4) against a cell-by-cell loop."""
import numpy as np
import pytest
from geoloc.vpr import spm_encode
from geoloc.vpr.spm import level_weights, spm_dim


def brute_force_spm(seg, num_classes, levels):
    h, w = seg.shape
    out = []
    for lvl in range(levels + 1):
        n = 2**lvl
        weight = 2.0**-levels if lvl == 0 else 2.0 ** (lvl - levels - 1)
        for a in range(n):
            for b in range(n):
                cell = seg[a * h // n : (a + 1) * h // n, b * w // n : (b + 1) * w // n]
                for c in range(num_classes):
                    out.append(weight * np.count_nonzero(cell == c))
    return np.array(out)


@pytest.mark.parametrize("shape,levels", [((37, 53), 0), ((37, 53), 2), ((64, 48), 3), ((5, 7), 3), ((33, 31), 4)])
def test_spm_matches_brute_force(shape, levels):
    rng = np.random.default_rng(sum(shape) + levels)
    seg = rng.integers(0, 8, size=shape)
    code = spm_encode(seg, 8, levels)
    assert code.shape == (spm_dim(8, levels),) and code.dtype == np.float32
    np.testing.assert_array_equal(code, brute_force_spm(seg, 8, levels))


def test_level_weights_eq4():
    np.testing.assert_array_equal(level_weights(2), [0.25, 0.25, 0.5])
    np.testing.assert_array_equal(level_weights(0), [1.0])
    np.testing.assert_array_equal(level_weights(3), [1 / 8, 1 / 8, 1 / 4, 1 / 2])


def test_default_is_the_papers_two_levels():
    seg = np.random.default_rng(0).integers(0, 8, size=(16, 16))
    np.testing.assert_array_equal(spm_encode(seg, 8), brute_force_spm(seg, 8, 2))


def test_level_zero_is_class_histogram():
    seg = np.array([[0, 1], [1, 2]], dtype=np.uint8)
    np.testing.assert_array_equal(spm_encode(seg, 3, 0), [1, 2, 1])


def test_spm_refuses_bad_labels_and_shapes():
    with pytest.raises(ValueError, match="labels must lie"):
        spm_encode(np.full((4, 4), 8), 8, 1)
    with pytest.raises(ValueError, match="H x W"):
        spm_encode(np.zeros((4, 4, 3), dtype=int), 8, 1)
    with pytest.raises(ValueError, match="integer"):
        spm_encode(np.zeros((4, 4)), 8, 1)
    with pytest.raises(ValueError, match="levels must be >= 0, got -1"):
        spm_encode(np.zeros((4, 4), dtype=int), 8, -1)
