"""Wheel odometry from true pose increments, with noise and drift.

Odometry noise model (the "alpha" model of Thrun, Burgard & Fox, Probabilistic Robotics,
§5.4, on the increment expressed in the robot frame): for a true increment
``u = x_{k-1}^-1 ∘ x_k = (dx, dy, dtheta)`` with travelled distance ``d = |(dx, dy)|``,

- ``dx, dy`` get independent Gaussian errors of std ``translation_sigma_per_m * d``,
- ``dtheta`` gets a Gaussian error of std
  ``rotation_sigma_per_rad * |dtheta| + rotation_sigma_per_m * d``,
- systematic drift: ``(dx, dy)`` are scaled by ``1 + translation_scale_bias`` and
  ``dtheta`` gains ``rotation_bias_rad_per_m * d``.

The odometry pose is the composition of the noisy increments. :meth:`OdometryModel.biased`
builds a drifting model from the figures quoted for real robots (a scale error in per cent,
a heading drift in degrees per metre); :data:`ACCURATE_ODOMETRY` is a near-perfect one.

Note that the standard deviations are per increment: the accumulated random error over a
path depends on how it is cut into increments (the scan rate); the bias does not.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from iceg_common.errors import ConfigError
from iceg_common.se2 import between, compose

FloatArray = NDArray[np.float64]


class OdometryModel(BaseModel):
    """Wheel-odometry noise and drift; see the module docstring for the model."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    translation_sigma_per_m: float = Field(
        default=0.05,
        ge=0.0,
        description="Std of each of dx, dy errors per metre of the increment (m/m); "
        "Probabilistic Robotics §5.4 alpha model.",
    )
    rotation_sigma_per_rad: float = Field(
        default=0.05,
        ge=0.0,
        description="Std of the heading error per radian turned in the increment (rad/rad).",
    )
    rotation_sigma_per_m: float = Field(
        default=0.01,
        ge=0.0,
        description="Std of the heading error per metre driven in the increment (rad/m).",
    )
    translation_scale_bias: float = Field(
        default=0.0,
        gt=-1.0,
        description="Systematic scale error of the distance (e.g. 0.01: wheels 1% too large).",
    )
    rotation_bias_rad_per_m: float = Field(
        default=0.002,
        description="Systematic heading drift per metre driven, rad/m (uneven wheel radii).",
    )
    start: Literal["true", "zero"] = Field(
        default="true",
        description="Odometry frame: 'true' starts at the true first pose, 'zero' at (0,0,0).",
    )

    @classmethod
    def biased(
        cls,
        scale_error: float = 0.01,
        heading_drift_deg_per_m: float = 0.4,
        noise: bool = True,
        start: Literal["true", "zero"] = "true",
    ) -> OdometryModel:
        """A drifting wheel odometry: distances scaled by ``1 + scale_error`` and a heading
        drift of ``heading_drift_deg_per_m`` degrees per metre driven (converted to rad/m
        here, the only place degrees enter), plus the default white noise unless
        ``noise=False``.

        Typical values for an uncalibrated differential drive (issue 11): 1–2 % scale error,
        0.3–0.5 deg/m heading drift (Borenstein & Feng 1996, UMBmark: unequal wheel
        diameters give a heading drift proportional to the distance driven).

        Raises:
            pydantic.ValidationError: ``scale_error <= -1``.
        """
        sig = {} if noise else dict.fromkeys(_SIGMA_FIELDS, 0.0)
        return cls(
            translation_scale_bias=scale_error,
            rotation_bias_rad_per_m=math.radians(heading_drift_deg_per_m),
            start=start,
            **sig,
        )

    def increment_sigmas(self, increments: ArrayLike) -> FloatArray:
        """Noise standard deviations ``(..., 3)`` for true increments ``(..., 3)``
        ``[dx_m, dy_m, dtheta_rad]`` in the robot frame."""
        u = np.asarray(increments, dtype=np.float64)
        d = np.hypot(u[..., 0], u[..., 1])
        sig_t = self.translation_sigma_per_m * d
        sig_r = self.rotation_sigma_per_rad * np.abs(u[..., 2]) + self.rotation_sigma_per_m * d
        return np.stack([sig_t, sig_t, sig_r], axis=-1)

    def increment_covariance(self, increment: ArrayLike) -> FloatArray:
        """``(3, 3)`` float64 covariance of the odometry increment error for a true
        increment ``(3,)`` (robot frame of the earlier pose; ``(x, y, theta)`` order).
        The bias is not included (it is systematic)."""
        return np.diag(self.increment_sigmas(increment) ** 2)

    def biased_increments(self, increments: ArrayLike) -> FloatArray:
        """Increments ``(..., 3)`` with the systematic drift applied (no random noise)."""
        u = np.array(increments, dtype=np.float64)
        d = np.hypot(u[..., 0], u[..., 1])
        u[..., :2] *= 1.0 + self.translation_scale_bias
        u[..., 2] += self.rotation_bias_rad_per_m * d
        return u

    def simulate(self, true_poses: ArrayLike, rng: np.random.Generator) -> FloatArray:
        """Odometry poses for a true trajectory.

        Args:
            true_poses: ``(N, 3)`` float64 true robot poses, world frame.
            rng: Source of the increment noise (``3 (N - 1)`` normal draws).

        Returns:
            ``(N, 3)`` float64 odometry poses ``[x_m, y_m, theta_rad]`` in the odometry frame
            (starting at ``true_poses[0]`` or at zero, per :attr:`start`).

        Raises:
            ConfigError: ``true_poses`` is not ``(N >= 1, 3)``.
        """
        x = np.asarray(true_poses, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != 3 or x.shape[0] < 1:
            raise ConfigError(f"true_poses must have shape (N >= 1, 3), got {x.shape}")
        u = between(x[:-1], x[1:])
        noisy = self.biased_increments(u) + rng.standard_normal(u.shape) * self.increment_sigmas(u)
        out = np.empty_like(x)
        out[0] = x[0] if self.start == "true" else 0.0
        for k in range(1, x.shape[0]):  # composition is sequential over scans
            out[k] = compose(out[k - 1], noisy[k - 1])
        return out


_SIGMA_FIELDS = ("translation_sigma_per_m", "rotation_sigma_per_rad", "rotation_sigma_per_m")

#: Near-perfect wheel odometry (no bias; 0.5 % distance noise, 0.5 % turn noise, 0.5 mrad/m):
#: for worlds that isolate a scan-matching error from odometry drift.
ACCURATE_ODOMETRY = OdometryModel(
    translation_sigma_per_m=0.005,
    rotation_sigma_per_rad=0.005,
    rotation_sigma_per_m=0.0005,
    rotation_bias_rad_per_m=0.0,
)
