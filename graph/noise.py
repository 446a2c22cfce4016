"""Odometry noise model: a covariance that grows with the distance and rotation travelled."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graph.config import OdometryNoiseConfig
from iceg_common.errors import GraphError
from iceg_common.se2 import wrap_float


def odometry_covariance(
    delta: ArrayLike, config: OdometryNoiseConfig | None = None
) -> NDArray[np.float64]:
    """Covariance of an odometry measurement ``delta = pose_i^-1 ∘ pose_j``.

    Model (Thrun, Burgard & Fox, *Probabilistic Robotics*, 2005, §5.4, linear in the motion
    with additive floors; parameters in :class:`graph.OdometryNoiseConfig`)::

        dist_m          = hypot(dx, dy)
        sigma_xy_m      = sigma_xy_base_m + sigma_xy_per_distance_m_per_m * dist_m
        sigma_theta_rad = sigma_theta_base_rad + sigma_theta_per_rotation * |wrap(dtheta)|
                          + sigma_theta_per_distance_rad_per_m * dist_m
        cov             = diag(sigma_xy_m², sigma_xy_m², sigma_theta_rad²)

    The translation noise is isotropic, so the covariance is the same in the frame of
    ``pose_i`` and in the tangent space of the measurement (the frame of
    :meth:`graph.PoseGraph.add_between`).

    Args:
        delta: ``(3,)`` float ``[dx_m, dy_m, dtheta_rad]``, the motion between two nodes in the
            frame of the first.
        config: noise parameters; defaults to ``OdometryNoiseConfig()``.

    Returns:
        ``(3, 3)`` float64 covariance, ``(x, y, theta)`` order, units m² and rad².

    Raises:
        GraphError: ``delta`` is not a finite ``(3,)`` vector.
    """
    cfg = config if config is not None else OdometryNoiseConfig()
    d = np.asarray(delta, dtype=np.float64)
    # floats from here: a tenth of numpy's 0-d calls, the same bits (wrap_float)
    values = d.tolist() if d.shape == (3,) else []
    if not values or not all(math.isfinite(v) for v in values):
        raise GraphError(
            f"odometry_covariance: delta must be a finite (3,) [dx_m, dy_m, dtheta_rad], "
            f"got shape {d.shape} and values {d!r}"
        )
    dx, dy, dtheta = values
    dist_m = math.hypot(dx, dy)
    dtheta_rad = abs(wrap_float(dtheta))
    sigma_xy_m = cfg.sigma_xy_base_m + cfg.sigma_xy_per_distance_m_per_m * dist_m
    sigma_theta_rad = (
        cfg.sigma_theta_base_rad
        + cfg.sigma_theta_per_rotation_deg_per_deg * dtheta_rad
        + cfg.sigma_theta_per_distance_rad_per_m * dist_m
    )
    cov = np.zeros((3, 3))
    cov[0, 0] = cov[1, 1] = sigma_xy_m**2
    cov[2, 2] = sigma_theta_rad**2
    return cov
