"""The calibrator, ECE and the coverage-accuracy curve against hand values and brute-force loops."""

import numpy as np
import pytest

from geoloc.eval.calibration import (Calibrator, coverage_accuracy, expected_calibration_error, fit_calibrator,
                                     retrieval_features)


def brute_ece(p, y, bins=15):
    """Sort, cut into `bins` runs of sizes n//bins or n//bins + 1 (the larger ones first), sum the weighted gaps."""
    order = sorted(range(len(p)), key=lambda i: (p[i], i))
    n, total, start = len(p), 0.0, 0
    for b in range(bins):
        size = n // bins + (1 if b < n % bins else 0)
        run = order[start:start + size]
        start += size
        if run:
            total += len(run) / n * abs(sum(p[i] for i in run) / len(run) - sum(y[i] for i in run) / len(run))
    return total


def test_ece_of_a_known_miscalibration_by_hand():
    # every answer claims 0.9, 60% are right: a gap of 0.3 in every bin
    p = np.full(150, 0.9)
    y = np.arange(150) % 5 < 3
    assert expected_calibration_error(p, y) == pytest.approx(0.3)
    # two bins by hand: {0.1, 0.2} with 1 right -> |0.15 - 0.5| = 0.35; {0.8, 0.9} with 2 right -> |0.85 - 1| = 0.15
    assert expected_calibration_error([0.9, 0.1, 0.8, 0.2], [1, 0, 1, 1], bins=2) == pytest.approx(0.25)


def test_ece_against_brute_force_loop():
    rng = np.random.default_rng(0)
    for n in (1, 7, 15, 16, 100, 451):
        p = rng.random(n).round(2)  # ties included
        y = rng.random(n) < 0.5
        assert expected_calibration_error(p, y) == pytest.approx(brute_ece(list(p), list(y)), abs=1e-12)


def test_perfectly_calibrated_source_has_ece_near_zero_and_a_miscalibrated_one_does_not():
    rng = np.random.default_rng(1)
    p = rng.random(200_000)
    y = rng.random(200_000) < p
    assert expected_calibration_error(p, y) < 0.005
    assert expected_calibration_error(p ** 2, y) > 0.1  # under-confident by p - p^2: 1/6 on average


def test_coverage_accuracy_against_brute_force():
    rng = np.random.default_rng(2)
    p, y = rng.random(50), rng.random(50) < 0.4
    coverage, accuracy = coverage_accuracy(p, y)
    for k in range(1, 51):
        kept = sorted(range(50), key=lambda i: -p[i])[:k]
        assert coverage[k - 1] == pytest.approx(k / 50)
        assert accuracy[k - 1] == pytest.approx(np.mean([y[i] for i in kept]))
    assert accuracy[-1] == pytest.approx(y.mean())


def test_fit_recovers_a_logistic_source_and_is_calibrated_on_fresh_answers():
    rng = np.random.default_rng(3)

    def answers(n):
        x = np.stack([rng.normal(0.5, 0.2, n), rng.exponential(0.05, n)], axis=1)
        truth = 1 / (1 + np.exp(-(8 * (x[:, 0] - 0.5) + 30 * x[:, 1] - 1)))
        return x, rng.random(n) < truth, truth

    x, y, _ = answers(20_000)
    calibrator = fit_calibrator(x, y, "top1", rule="synthetic")
    x_test, y_test, truth = answers(20_000)
    p = calibrator.probability(x_test)
    assert np.abs(p - truth).max() < 0.05
    assert expected_calibration_error(p, y_test) < 0.02
    assert calibrator.fitted_on == {"answers": 20_000, "right": int(y.sum()), "rule": "synthetic"}
    # a constant guess at the base rate is not: the features carry the signal
    assert expected_calibration_error(np.full(len(y_test), y.mean()), y_test) < 0.02
    assert np.abs(np.full(len(y_test), y.mean()) - truth).max() > 0.3


def test_fit_stays_finite_on_separable_labels_and_round_trips_json():
    x = np.array([[0.1, 0.0], [0.2, 0.01], [0.8, 0.3], [0.9, 0.4]])
    calibrator = fit_calibrator(x, [0, 0, 1, 1], "top1", condition={"heading": "given"})
    p = calibrator.probability(x)
    assert np.isfinite(p).all() and p[0] < 0.5 < p[3]
    again = Calibrator.from_json(calibrator.to_json())
    assert again == calibrator and np.array_equal(again.probability(x), p)


def test_bad_input_is_refused_by_name():
    with pytest.raises(ValueError, match="probabilities"):
        expected_calibration_error([1.5], [1])
    with pytest.raises(ValueError, match="two"):
        coverage_accuracy([0.5, 0.5], [1])
    with pytest.raises(ValueError, match="not a calibrator record"):
        Calibrator.from_json({"target": "top1"}, "calibration.json")
    with pytest.raises(ValueError, match="finite"):
        Calibrator("top1", ("a",), [0.0], [1.0], [float("nan")], 0.0)
    with pytest.raises(ValueError, match="n x 2"):
        fit_calibrator(np.zeros((3, 1)), [0, 1, 0], "top1")


def test_retrieval_features():
    f = retrieval_features([[0.9, 0.7, 0.1], [0.5, float("-inf"), float("-inf")]])
    assert np.allclose(f, [[0.9, 0.2], [0.5, 1.5]])
    assert np.allclose(retrieval_features([[0.3]]), [[0.3, 1.3]])
