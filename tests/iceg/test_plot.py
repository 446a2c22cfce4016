"""Plot helpers draw what they are given (checked on the returned artists)."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.figure import Figure

from iceg import plot


def test_covariance_ellipse_axes_are_n_sigma_wide() -> None:
    # Hand-computed: sigma_x = 0.1 m, sigma_y = 0.2 m in the body frame of a pose heading
    # +90 deg: in the map frame the major axis (2 * 3 * 0.2 = 1.2 m) lies along x.
    ax = Figure().add_subplot()
    cov = np.diag([0.01, 0.04, 0.001])
    (ell,) = plot.covariance_ellipses(ax, [[1.0, 2.0, np.pi / 2]], [cov], n_sigma=3.0)
    assert ell.center == pytest.approx((1.0, 2.0))
    assert ell.width == pytest.approx(1.2)
    assert ell.height == pytest.approx(0.6)
    assert np.cos(np.radians(ell.angle)) ** 2 == pytest.approx(1.0)


def test_relation_error_histogram_counts_finite_rows() -> None:
    ax = Figure().add_subplot()
    per = np.array([[0.01, 0.1], [0.02, 0.2], [np.nan, np.nan], [0.5, 1.0]])
    bars = plot.relation_errors(ax, per, bins=5)
    assert sum(b.get_height() for b in bars) == 3


def test_nees_cdf_steps_through_the_finite_values_to_one() -> None:
    ax = Figure().add_subplot()
    line, ref = plot.nees_cdf(ax, [4.0, 1.0, np.nan, 2.0], "scan_match")
    np.testing.assert_array_equal(line.get_xdata(), [1.0, 2.0, 4.0])
    np.testing.assert_allclose(line.get_ydata(), [1 / 3, 2 / 3, 1.0])
    assert line.get_label() == "scan_match (3)"
    # the reference is the chi-square (3 dof) CDF: 0.95 at its 95 % quantile 7.8147
    x, y = ref.get_xdata(), ref.get_ydata()
    assert np.interp(7.8147, x, y) == pytest.approx(0.95, abs=2e-3)
    assert ax.get_xscale() == "log"
