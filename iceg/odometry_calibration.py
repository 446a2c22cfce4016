"""Online calibration of systematic wheel-odometry errors from accepted scan matches.

A wheel odometry with unequal wheel radii, a wrong wheel radius or a wrong wheel base has
systematic errors that white-noise covariances do not describe: every step's distance is
off by the same fraction, and the heading drifts by a fixed angle per metre driven
(Borenstein & Feng 1996, "Measurement and correction of systematic odometry errors in mobile
robots", IEEE T-RA 12(6), UMBmark). Where the scan matcher fails, the odometry factor is the
only link between two nodes and carries that error into the map in full: the straight walls
of a building bend.

The calibration follows the idea of Censi, Franchi, Marchionni & Oriolo 2013, "Simultaneous
calibration of odometry and sensor parameters for mobile robots" (IEEE T-RO 29(2)), and
Antonelli, Chiaverini & Fusco 2005 (IEEE T-RO 21(5)): the relation between the odometry
increment and the true one is linear in a few parameters, so a (weighted, robust) least
squares against an exteroceptive measurement of the motion estimates them. Here the
measurement is the accepted local scan match of each keyframe, and the model, per keyframe
step with raw odometry increment ``(tx_o, ty_o, dtheta_o)`` in the frame of the earlier
node and signed distance ``d_o = sign(tx_o) * hypot(tx_o, ty_o)`` (negative when reversing,
where unequal wheel radii turn the other way), is::

    t      = kappa * t_o                              (distance scale)
    dtheta = gamma * dtheta_o - beta * d_o            (turn scale, heading drift per metre)

with ``kappa = 1 / (1 + scale error)``. Both equations are linear in their parameters and
independent, so two recursive weighted least squares (a scalar for ``kappa``, a 2-vector for
``(gamma, beta)``) with a Gaussian prior at the identity estimate them. Each observation's
weight is the inverse of the scan-match covariance plus the configured odometry noise
(``graph.odometry_covariance``); a Huber weight on the innovation (Huber 1964) limits wrong
matches; and the residual variance factor (reduced chi-square) of each equation scales the
parameters' covariance and, when the odometry is noisier than configured, its covariance.

Parameters are constant over a run (no forgetting): wheel radii and base change slowly.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidatorFunctionWrapHandler,
    field_validator,
)

from graph import OdometryNoiseConfig

FloatArray = NDArray[np.float64]

logger = logging.getLogger(__name__)

__all__ = [
    "OdometryCalibrationConfig",
    "OdometryCalibrator",
    "SystematicError",
    "systematic_errors",
]

#: Standard deviations of its estimate by which a systematic error must exceed what the
#: odometry noise model allows before it is called beyond the model (the conventional three).
BEYOND_SIGMAS = 3.0


class OdometryCalibrationConfig(BaseModel):
    """Settings of :class:`OdometryCalibrator` (prior of the parameters, robust weight)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool | Literal["auto"] = Field(
        default="auto",
        description="Correct the odometry by its distance scale, turn scale and heading "
        "drift per metre as the accepted scan matches estimate them: true always, false "
        "never, 'auto' (the default) while one of them is beyond what the odometry noise "
        "model allows by three standard deviations of its estimate (systematic_errors). "
        "Always on, ACES with 1 % scale and 0.4 deg/m drift loses (seed 0: 0.189 -> 0.653 "
        "m ATE); with 'auto' it runs as uncorrected (its errors are within the model), and "
        "ACES with a 2 deg/m drift keeps its chain (4.38 / 0.18 / 6.04 -> 0.20 / 0.20 / "
        "0.18 m at seeds 0-2); docs/design.md, 'The odometry's systematic errors, corrected "
        "where beyond the model'.",
    )
    prior_scale_sigma: float = Field(
        default=0.05,
        gt=0.0,
        description="Prior standard deviation of the distance scale kappa around 1 "
        "(dimensionless; 0.05 = 5 %, well above the 1-2 % of an uncalibrated base).",
    )
    prior_turn_scale_sigma: float = Field(
        default=0.05,
        gt=0.0,
        description="Prior standard deviation of the turn scale gamma around 1.",
    )
    prior_heading_drift_sigma_deg_per_m: float = Field(
        default=2.0,
        gt=0.0,
        description="Prior standard deviation of the heading drift beta around 0 (deg/m; "
        "UMBmark-typical drifts are 0.1-1 deg/m).",
    )
    prior_dof: float = Field(
        default=2.0,
        gt=0.0,
        description="Weight, in observations, of the prior residual variance factor 1 (the "
        "configured odometry noise is right) in the estimated variance factor.",
    )
    huber_k: float = Field(
        default=1.345,
        gt=0.0,
        description="Huber threshold on the normalised innovation (1.345: 95 % efficiency "
        "under Gaussian noise; Huber 1964).",
    )

    @field_validator("enabled", mode="wrap")
    @classmethod
    def _true_false_or_auto(cls, value: Any, handler: ValidatorFunctionWrapHandler) -> Any:
        """One message for the three choices (pydantic gives one per member of the union)."""
        try:
            return handler(value)
        except ValidationError:
            raise ValueError(f"must be true, false or 'auto', not {value!r}") from None

    @property
    def prior_heading_drift_sigma_rad_per_m(self) -> float:
        """``prior_heading_drift_sigma_deg_per_m`` in radians per metre."""
        return math.radians(self.prior_heading_drift_sigma_deg_per_m)


@dataclass
class _VarianceFactor:
    """Running reduced chi-square of normalised innovations, with a prior of 1."""

    prior_dof: float
    chi2: float = 0.0
    dof: float = 0.0

    @property
    def value(self) -> float:
        return (self.prior_dof + self.chi2) / (self.prior_dof + self.dof)

    def add(self, chi2: float, dof: float, weight: float) -> None:
        self.chi2 += weight * chi2
        self.dof += weight * dof


@dataclass
class _Rls:
    """Information-form linear least squares ``y = h . p`` with a Gaussian prior, for one
    or two parameters (the arithmetic is written out in floats: a keyframe's observation
    costs a few microseconds, not the tens that numpy's calls on 2 x 2 arrays take)."""

    info: FloatArray  # (n, n), n = 1 or 2
    vec: FloatArray  # (n,) information vector
    n_obs: int = 0

    @property
    def params(self) -> FloatArray:
        """``(n,)`` the estimate ``info^-1 vec`` (Cramer's rule for two)."""
        if self.info.shape[0] == 1:
            return self.vec / self.info[0]
        (a, b), (c, d) = self.info.tolist()
        v0, v1 = self.vec.tolist()
        det = a * d - b * c
        return np.array([(d * v0 - b * v1) / det, (a * v1 - c * v0) / det])

    @property
    def cov(self) -> FloatArray:
        """Covariance of the parameters for unit residual variance factor."""
        return np.asarray(np.linalg.inv(self.info), dtype=np.float64)

    def add_pair(
        self, h: tuple[float, float], y: tuple[float, float], w: tuple[float, float, float, float]
    ) -> None:
        """Two observations of the one parameter: ``y = h p`` + noise of information ``w``
        (a 2 x 2 matrix, row by row): ``info += h^T w h``, ``vec += h^T w y``."""
        a, b, c, d = w
        (h0, h1), (y0, y1) = h, y
        self.info[0, 0] += h0 * (a * h0 + b * h1) + h1 * (c * h0 + d * h1)
        self.vec[0] += h0 * (a * y0 + b * y1) + h1 * (c * y0 + d * y1)
        self.n_obs += 1

    def add_row(self, h: tuple[float, float], y: float, w: float) -> None:
        """One observation of the two parameters: ``y = h . p`` + noise of information
        ``w``."""
        h0, h1 = h
        self.info[0, 0] += h0 * w * h0
        self.info[0, 1] += h0 * w * h1
        self.info[1, 0] += h1 * w * h0
        self.info[1, 1] += h1 * w * h1
        self.vec[0] += h0 * w * y
        self.vec[1] += h1 * w * y
        self.n_obs += 1


def _huber_weight(z: float, k: float) -> float:
    """Huber weight of a normalised residual ``z``."""
    return 1.0 if abs(z) <= k else k / abs(z)


def signed_distance(delta: ArrayLike) -> float:
    """Signed distance of an SE(2) increment ``(3,)``: ``hypot(dx, dy)``, negative when the
    increment goes backwards (``dx < 0``). Metres."""
    d = np.asarray(delta, dtype=np.float64)
    dist = math.hypot(d[0], d[1])
    return -dist if d[0] < 0.0 else dist


@dataclass
class OdometryCalibrator:
    """Recursive robust estimate of the odometry's distance scale ``kappa``, turn scale
    ``gamma`` and heading drift ``beta`` (rad per metre driven); see the module docstring.

    Use: :meth:`correct` every odometry increment before it becomes a prediction or a
    factor while :attr:`correcting`; :meth:`observe` every accepted scan match of a keyframe
    step with the raw odometry increment of the same step (whether or not it corrects).

    Args:
        config: Priors, robust weight and when to correct (:class:`OdometryCalibrationConfig`).
        noise: The run's odometry noise model, against which ``enabled: "auto"`` judges the
            estimates (:func:`systematic_errors`).
    """

    config: OdometryCalibrationConfig = field(default_factory=OdometryCalibrationConfig)
    noise: OdometryNoiseConfig = field(default_factory=OdometryNoiseConfig)
    _scale: _Rls = field(init=False)
    _heading: _Rls = field(init=False)
    _s2_t: _VarianceFactor = field(init=False)
    _s2_r: _VarianceFactor = field(init=False)
    _correcting: bool = field(init=False)

    def __post_init__(self) -> None:
        c = self.config
        i_k = 1.0 / c.prior_scale_sigma**2
        self._scale = _Rls(np.array([[i_k]]), np.array([i_k]))
        i_g = 1.0 / c.prior_turn_scale_sigma**2
        i_b = 1.0 / c.prior_heading_drift_sigma_rad_per_m**2
        self._heading = _Rls(np.diag([i_g, i_b]), np.array([i_g, 0.0]))
        self._s2_t = _VarianceFactor(c.prior_dof)
        self._s2_r = _VarianceFactor(c.prior_dof)
        self._correcting = c.enabled is True

    @property
    def correcting(self) -> bool:
        """Whether the odometry is to be corrected (:meth:`correct`) now: ``enabled`` true,
        or ``"auto"`` and one of the systematic errors, as the matches observed so far
        estimate them, beyond the noise model (:attr:`SystematicError.beyond_noise_model`).
        A function of the estimator's state, so a restored state gives the same answer."""
        return self._correcting

    def _update_correcting(self) -> None:
        if self.config.enabled != "auto":
            return
        beyond = [n for n, e in systematic_errors(self, self.noise).items() if e.beyond_noise_model]
        if bool(beyond) != self._correcting:
            logger.info(
                "odometry calibration: %s after %d matches (beyond the noise model: %s)",
                "correcting the odometry" if beyond else "no longer correcting the odometry",
                self.n_observations,
                ", ".join(beyond) or "none",
            )
        self._correcting = bool(beyond)

    # ------------------------------------------------------------------ estimates

    @property
    def scale(self) -> float:
        """Distance scale ``kappa`` (true distance / odometry distance)."""
        return float(self._scale.params[0])

    @property
    def turn_scale(self) -> float:
        """Turn scale ``gamma`` (true turn / odometry turn, without drift)."""
        return float(self._heading.params[0])

    @property
    def heading_drift_rad_per_m(self) -> float:
        """Heading drift ``beta``: odometry heading gain per signed metre driven, rad/m."""
        return float(self._heading.params[1])

    @property
    def n_observations(self) -> int:
        """Scan matches used so far."""
        return self._heading.n_obs

    def variance_factors(self) -> tuple[float, float]:
        """Reduced chi-square of the translation and heading innovations (1 = the
        configured odometry noise plus the scan-match covariance explain them)."""
        return self._s2_t.value, self._s2_r.value

    def parameter_covariance(self) -> tuple[float, FloatArray]:
        """Variance of ``kappa`` and ``(2, 2)`` covariance of ``(gamma, beta)``, each scaled
        by its residual variance factor (at least 1)."""
        var_k = float(self._scale.cov[0, 0]) * max(self._s2_t.value, 1.0)
        return var_k, self._heading.cov * max(self._s2_r.value, 1.0)

    def estimates_and_variances(self) -> tuple[float, float, float, float, float, float]:
        """``kappa``, ``gamma``, ``beta`` (rad/m) and their variances as
        :meth:`parameter_covariance` scales them, in floats (the inverses written out: the
        "auto" setting asks after every match, and numpy's 2 x 2 inverse costs most of a
        call there)."""
        (i_k,), (v_k,) = self._scale.info[0].tolist(), self._scale.vec.tolist()
        (a, b), (c, d) = self._heading.info.tolist()
        v0, v1 = self._heading.vec.tolist()
        det = a * d - b * c
        s2_t, s2_r = (max(v, 1.0) for v in self.variance_factors())
        return (
            v_k / i_k,
            (d * v0 - b * v1) / det,
            (a * v1 - c * v0) / det,
            s2_t / i_k,
            s2_r * d / det,
            s2_r * a / det,
        )

    # ------------------------------------------------------------------ state (sessions)

    def export_state(self) -> np.ndarray:
        """The whole estimator state as one ``(14,)`` float64 array (saved sessions):
        scale information ``(1, 1)`` and vector ``(1,)``, heading information ``(2, 2)`` and
        vector ``(2,)``, their observation counts, and the two variance factors' chi² / dof."""
        sc, hd = self._scale, self._heading
        return np.concatenate(
            [
                sc.info.ravel(),
                sc.vec,
                hd.info.ravel(),
                hd.vec,
                [sc.n_obs, hd.n_obs],
                [self._s2_t.chi2, self._s2_t.dof, self._s2_r.chi2, self._s2_r.dof],
            ]
        ).astype(np.float64)

    def restore_state(self, state: ArrayLike) -> None:
        """Restore an :meth:`export_state` array (same later corrections, bit for bit)."""
        v = np.asarray(state, dtype=np.float64).reshape(14)
        self._scale = _Rls(v[0:1].reshape(1, 1).copy(), v[1:2].copy(), int(v[8]))
        self._heading = _Rls(v[2:6].reshape(2, 2).copy(), v[6:8].copy(), int(v[9]))
        self._s2_t.chi2, self._s2_t.dof = float(v[10]), float(v[11])
        self._s2_r.chi2, self._s2_r.dof = float(v[12]), float(v[13])
        self._update_correcting()

    # ------------------------------------------------------------------ use

    def correct(self, delta: ArrayLike, cov: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Calibrated odometry increment and its covariance.

        Args:
            delta: ``(3,)`` raw odometry increment ``[dx_m, dy_m, dtheta_rad]`` in the frame
                of the earlier pose.
            cov: ``(3, 3)`` its configured noise covariance (``graph.odometry_covariance``).

        Returns:
            ``(delta (3,), cov (3, 3))``: the corrected increment and ``J cov J^T`` (scaled
            up by the residual variance factors where the odometry proved noisier than
            configured) plus the propagated uncertainty of the calibration parameters.
        """
        d = np.asarray(delta, dtype=np.float64)
        c = np.asarray(cov, dtype=np.float64)
        kappa, gamma, beta = self.scale, self.turn_scale, self.heading_drift_rad_per_m
        dist = signed_distance(d)
        out = np.array([kappa * d[0], kappa * d[1], gamma * d[2] - beta * dist])
        jac = np.diag([kappa, kappa, gamma])
        if dist != 0.0:
            jac[2, :2] = -beta * d[:2] / dist
        s2_t, s2_r = (max(v, 1.0) for v in self.variance_factors())
        inflate = np.sqrt(np.array([s2_t, s2_t, s2_r]))
        c = c * np.outer(inflate, inflate)
        var_k, cov_gb = self.parameter_covariance()
        jp_t = d[:2]
        jp_r = np.array([d[2], -dist])
        out_cov = jac @ c @ jac.T
        out_cov[:2, :2] += var_k * np.outer(jp_t, jp_t)
        out_cov[2, 2] += float(jp_r @ cov_gb @ jp_r)
        return out, out_cov

    def observe(
        self, delta: ArrayLike, odom_cov: ArrayLike, measured: ArrayLike, match_cov: ArrayLike
    ) -> None:
        """Use one accepted scan match of the same step as a raw odometry increment.

        Args:
            delta: ``(3,)`` raw odometry increment of the step (frame of the earlier node).
            odom_cov: ``(3, 3)`` its configured noise covariance.
            measured: ``(3,)`` the scan-match relative pose of the step (same frame).
            match_cov: ``(3, 3)`` the scan match's covariance.
        """
        d = np.asarray(delta, dtype=np.float64)
        z = np.asarray(measured, dtype=np.float64)
        cov = np.asarray(odom_cov, dtype=np.float64) + np.asarray(match_cov, dtype=np.float64)
        self._observe_translation(d, z, cov[:2, :2])
        self._observe_heading(d, z, float(cov[2, 2]))
        self._update_correcting()

    def _observe_translation(self, d: FloatArray, z: FloatArray, cov: FloatArray) -> None:
        (a, b), (c, e) = cov.tolist()
        det = a * e - b * c
        i00, i01, i10, i11 = e / det, -b / det, -c / det, a / det  # cov^-1
        h = (float(d[0]), float(d[1]))
        y = (float(z[0]), float(z[1]))
        kappa = self.scale
        r0, r1 = y[0] - kappa * h[0], y[1] - kappa * h[1]
        chi2 = r0 * (i00 * r0 + i01 * r1) + r1 * (i10 * r0 + i11 * r1)
        s2 = self._s2_t.value
        w = _huber_weight(math.sqrt(chi2 / (2.0 * s2)), self.config.huber_k)
        self._s2_t.add(chi2, 2.0, w)
        self._scale.add_pair(h, y, (w * i00, w * i01, w * i10, w * i11))

    def _observe_heading(self, d: FloatArray, z: FloatArray, var: float) -> None:
        dth, zth = float(d[2]), float(z[2])
        dtheta = math.atan2(math.sin(zth - dth), math.cos(zth - dth)) + dth
        h = (dth, -signed_distance(d))
        p0, p1 = self._heading.params.tolist()
        r = dtheta - (h[0] * p0 + h[1] * p1)
        s2 = self._s2_r.value
        w = _huber_weight(r / math.sqrt(var * s2), self.config.huber_k)
        self._s2_r.add(r * r / var, 1.0, w)
        self._heading.add_row(h, dtheta, w / var)


@dataclass(frozen=True)
class SystematicError:
    """One systematic error of the odometry as the scans measure it (:func:`systematic_errors`).

    Attributes:
        value: The estimate (a fraction, or degrees per metre).
        std: Its standard deviation, same unit.
        allowed: What the odometry noise model allows for, same unit.
    """

    value: float
    std: float
    allowed: float

    @property
    def beyond_noise_model(self) -> bool:
        """Larger than ``allowed`` by more than :data:`BEYOND_SIGMAS` standard deviations."""
        return abs(self.value) - BEYOND_SIGMAS * self.std > self.allowed


def systematic_errors(
    calibrator: OdometryCalibrator, noise: OdometryNoiseConfig
) -> dict[str, SystematicError]:
    """The odometry's systematic errors as the run's accepted scan matches measure them
    (:class:`OdometryCalibrator`, which estimates whether or not it corrects), against what
    the odometry noise model (``graph.odometry_covariance``) allows for: per metre driven, a
    translation error of ``sigma_xy_per_distance_m_per_m`` and a heading error of
    ``sigma_theta_per_distance_deg_per_m``; per unit turned,
    ``sigma_theta_per_rotation_deg_per_deg``.
    One beyond the model biases every odometry factor beyond its covariance, the same way
    at every step, so the walls bend (Borenstein & Feng 1996); the online calibration is
    what corrects it.

    Args:
        calibrator: The run's calibrator (``Slam.odometry_calibrator``).
        noise: The run's odometry noise model (``IcegConfig.odometry_noise``).

    Returns:
        ``distance_scale_error`` (``1 / kappa - 1``: the odometry's distance over the true
        one, less 1), ``turn_scale_error`` (``1 / gamma - 1``) and
        ``heading_drift_deg_per_m`` (``beta``), their standard deviations to first order.
        Raises nothing.
    """
    kappa, gamma, beta, var_k, var_g, var_b = calibrator.estimates_and_variances()
    return {
        "distance_scale_error": SystematicError(
            1.0 / kappa - 1.0, math.sqrt(var_k) / kappa**2, noise.sigma_xy_per_distance_m_per_m
        ),
        "turn_scale_error": SystematicError(
            1.0 / gamma - 1.0,
            math.sqrt(var_g) / gamma**2,
            noise.sigma_theta_per_rotation_deg_per_deg,
        ),
        "heading_drift_deg_per_m": SystematicError(
            math.degrees(beta),
            math.degrees(math.sqrt(var_b)),
            noise.sigma_theta_per_distance_deg_per_m,
        ),
    }
