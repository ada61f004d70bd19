"""Error metrics on synthetic data with known answers."""

import numpy as np
import pytest

from lgs_wfs_ros.analysis import metrics


def test_known_errors():
    truth = np.zeros((4, 2))
    est = np.array([[3.0, 4.0], [-3.0, -4.0], [0.0, 1.0], [np.nan, 0.0]])
    s = metrics.summarize(metrics.errors(est, truth), mas_per_px=500)
    assert s["n"] == 3 and s["n_nan"] == 1
    assert s["mean_euclid"] == pytest.approx((5 + 5 + 1) / 3)
    assert s["mae_x"] == pytest.approx(2.0)
    assert s["mae_y"] == pytest.approx(3.0)
    assert s["mae"] == pytest.approx(2.5)
    assert s["rms"] == pytest.approx(np.sqrt((25 + 25 + 1) / 3))
    assert s["bias_x"] == pytest.approx(0.0) and s["bias_y"] == pytest.approx(1 / 3)
    assert s["mean_euclid_mas"] == pytest.approx(500 * 11 / 3)


def test_gaussian_errors_match_theory():
    rng = np.random.default_rng(0)
    sigma = 0.1
    err = rng.normal(0.05, sigma, size=(200000, 2))
    s = metrics.summarize(err)
    assert s["mae"] == pytest.approx(np.sqrt(2 / np.pi) * sigma * np.exp(-0.125)
                                     + 0.05 * (1 - 2 * 0.3085375), rel=0.01)
    assert s["bias_x"] == pytest.approx(0.05, abs=0.001)
    assert s["rms"] == pytest.approx(np.sqrt(2 * (sigma ** 2 + 0.05 ** 2)), rel=0.01)


def test_shape_mismatch_is_an_error():
    with pytest.raises(ValueError):
        metrics.errors(np.zeros((3, 2)), np.zeros((4, 2)))


def test_by_radius_and_table():
    r = np.array([1.0, 5.0, 9.0])
    err = np.array([[[1.0, 0.0], [0.0, 2.0], [3.0, 0.0]]])
    rows = metrics.by_radius(err, r, [0, 4, 8, 12])
    assert [row["mean_euclid"] for row in rows] == [1.0, 2.0, 3.0]
    text = metrics.table({"cog": metrics.summarize(err)})
    assert "cog" in text and "2.0000" in text
