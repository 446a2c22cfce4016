"""odometry_covariance and the graph configs: values computed by hand from the documented model."""

from __future__ import annotations

import math

import numpy as np
import pydantic
import pytest

from graph import GraphConfig, OdometryNoiseConfig, odometry_covariance
from iceg_common.errors import GraphError


def test_odometry_covariance_matches_hand_computed_model() -> None:
    # delta = (3, 4, 0.5): dist = 5 m, |dtheta| = 0.5 rad. Defaults (config.py):
    # sigma_xy = 0.01 + 0.02 * 5 = 0.11 m
    # sigma_theta = 0.5 deg + 0.05 * 0.5 rad + 0.5 deg/m * 5 m = 3 deg + 0.025 rad
    cov = odometry_covariance([3.0, 4.0, 0.5])
    sigma_theta = math.radians(3.0) + 0.025
    np.testing.assert_allclose(cov, np.diag([0.11**2, 0.11**2, sigma_theta**2]), rtol=1e-12)


def test_odometry_covariance_custom_config_and_angle_wrapping() -> None:
    cfg = OdometryNoiseConfig(
        sigma_xy_base_m=0.1,
        sigma_xy_per_distance_m_per_m=0.0,
        sigma_theta_base_deg=1.0,
        sigma_theta_per_rotation_deg_per_deg=0.5,
        sigma_theta_per_distance_deg_per_m=0.0,
    )
    # dtheta = 2 pi - 0.2 wraps to -0.2: sigma_theta = 1 deg + 0.5 * 0.2 rad
    cov = odometry_covariance([0.0, 0.0, 2.0 * math.pi - 0.2], cfg)
    expected_theta = math.radians(1.0) + 0.1
    np.testing.assert_allclose(np.diag(cov), [0.01, 0.01, expected_theta**2], rtol=1e-12)
    # zero motion keeps the floors: positive definite
    still = odometry_covariance([0.0, 0.0, 0.0], cfg)
    np.testing.assert_allclose(np.diag(still), [0.01, 0.01, math.radians(1.0) ** 2])


def test_odometry_covariance_grows_with_distance_and_rotation() -> None:
    # truth: the model is monotone in |distance| and |rotation| (every coefficient >= 0)
    small = odometry_covariance([0.1, 0.0, 0.01])
    far = odometry_covariance([1.0, 0.0, 0.01])
    turned = odometry_covariance([0.1, 0.0, 1.0])
    assert far[0, 0] > small[0, 0] and far[2, 2] > small[2, 2]
    assert turned[2, 2] > small[2, 2] and turned[0, 0] == pytest.approx(small[0, 0])


def test_odometry_covariance_has_the_bits_of_the_numpy_expressions() -> None:
    # The float path (Python's modulo for the wrap) against the numpy wrap it replaced, bit
    # for bit, on random deltas and headings at and beyond +-pi (where the wrap decides).
    rng = np.random.default_rng(0)
    deltas = rng.normal(0.0, [0.5, 0.5, 4.0], (5000, 3))
    deltas[::5, 2] = rng.choice([np.pi, -np.pi, 3 * np.pi, 2 * np.pi - 1e-12], 1000)
    cfg = OdometryNoiseConfig()
    for d in deltas:
        dist = math.hypot(d[0], d[1])
        turn = np.abs((d[2] + np.pi) % (2.0 * np.pi) - np.pi)
        s_xy = cfg.sigma_xy_base_m + cfg.sigma_xy_per_distance_m_per_m * dist
        s_th = (
            cfg.sigma_theta_base_rad
            + cfg.sigma_theta_per_rotation_deg_per_deg * turn
            + cfg.sigma_theta_per_distance_rad_per_m * dist
        )
        want = np.diag([s_xy**2, s_xy**2, s_th**2])
        assert odometry_covariance(d, cfg).tobytes() == want.tobytes(), d


@pytest.mark.parametrize(
    "bad", [[1.0, 2.0], [1.0, np.nan, 0.0], [[1.0, 2.0, 3.0]], [0.0, 0.0, np.inf]]
)
def test_odometry_covariance_rejects_bad_delta(bad: list) -> None:
    with pytest.raises(GraphError, match=r"finite \(3,\)"):
        odometry_covariance(bad)


def test_configs_are_frozen_validated_and_convert_degrees() -> None:
    with pytest.raises(pydantic.ValidationError):
        GraphConfig(relinearize_threshold=-1.0)
    with pytest.raises(pydantic.ValidationError):
        GraphConfig(unknown_key=1)  # type: ignore[call-arg]
    with pytest.raises(pydantic.ValidationError):
        OdometryNoiseConfig(sigma_xy_base_m=0.0)
    cfg = GraphConfig(prior_sigma_theta_deg=180.0)
    assert cfg.prior_sigma_theta_rad == pytest.approx(math.pi)
    with pytest.raises(pydantic.ValidationError):
        cfg.relinearize_skip = 3  # type: ignore[misc]
