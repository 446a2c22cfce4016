"""Trajectory evaluation: the relation metric of Kümmerle et al. 2009, and errors against a
ground-truth trajectory.

Kümmerle, Steder, Dornhege, Ruhnke, Grisetti, Stachniss, Kleiner: "On measuring the accuracy
of SLAM algorithms", Autonomous Robots 27:387-407, 2009. For every relation
``(t1, t2, delta*)`` the estimate gives ``delta = x(t1)^-1 ∘ x(t2)`` and the error is
``e = delta*^-1 ∘ delta``; translational ``|e_xy|`` (m) and rotational ``|e_theta|`` (deg)
errors are averaged, with their squared forms.

Absolute trajectory error and RPE through ``evo`` are available with the optional ``eval``
extra (evo is GPL and never a hard dependency).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from frontends.relations import match_stamps
from iceg_common import se2
from iceg_common.errors import EvaluationError

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class RelationErrors:
    """Summary of the relation metric (Kümmerle et al. 2009, eq. 2 and Table 2 columns).

    Attributes:
        n_relations: relations in the file.
        n_matched: relations whose two timestamps both matched a trajectory stamp.
        trans_mean_m, trans_std_m: mean and std of ``|e_xy|``.
        rot_mean_deg, rot_std_deg: mean and std of ``|e_theta|``.
        trans_sq_mean_m2, trans_sq_std_m2: mean and std of ``|e_xy|^2``.
        rot_sq_mean_deg2, rot_sq_std_deg2: mean and std of ``e_theta^2``.
        trans_max_m, rot_max_deg: worst relation.
    """

    n_relations: int
    n_matched: int
    trans_mean_m: float
    trans_std_m: float
    rot_mean_deg: float
    rot_std_deg: float
    trans_sq_mean_m2: float
    trans_sq_std_m2: float
    rot_sq_mean_deg2: float
    rot_sq_std_deg2: float
    trans_max_m: float
    rot_max_deg: float

    def as_dict(self) -> dict[str, float | int]:
        """Plain dict for JSON output."""
        return asdict(self)


def relation_errors(
    stamps_s: ArrayLike,
    poses: ArrayLike,
    relation_stamps_s: ArrayLike,
    relation_deltas: ArrayLike,
    tolerance_s: float = 1e-3,
) -> tuple[RelationErrors, FloatArray]:
    """Score a trajectory with benchmark relations (Kümmerle et al. 2009).

    Args:
        stamps_s: ``(N,)`` trajectory timestamps, seconds, non-decreasing.
        poses: ``(N, 3)`` robot poses ``[x_m, y_m, theta_rad]`` in any fixed world frame.
        relation_stamps_s: ``(M, 2)`` ``[t1, t2]`` of each relation.
        relation_deltas: ``(M, 3)`` true ``x(t1)^-1 ∘ x(t2)``.
        tolerance_s: timestamp matching tolerance.

    Returns:
        ``(summary, per_relation)`` where ``per_relation`` is ``(M, 2)``
        ``[trans_err_m, rot_err_deg]`` (NaN for unmatched relations).

    Raises:
        EvaluationError: the trajectory is empty or no relation matches it.
    """
    t = np.asarray(stamps_s, dtype=np.float64)
    x = np.asarray(poses, dtype=np.float64)
    rs = np.asarray(relation_stamps_s, dtype=np.float64).reshape(-1, 2)
    rd = np.asarray(relation_deltas, dtype=np.float64).reshape(-1, 3)
    if t.size == 0 or x.shape != (t.size, 3):
        raise EvaluationError(
            f"trajectory must have one (x, y, theta) pose per stamp; got {x.shape} poses "
            f"for {t.size} stamps"
        )
    if np.any(np.diff(t) < 0):
        raise EvaluationError("trajectory stamps must be non-decreasing")
    i1, ok1 = match_stamps(rs[:, 0], t, tolerance_s)
    i2, ok2 = match_stamps(rs[:, 1], t, tolerance_s)
    ok = ok1 & ok2
    n_matched = int(ok.sum())
    if n_matched == 0:
        raise EvaluationError(
            f"none of the {len(rs)} relations matches a trajectory timestamp within "
            f"{tolerance_s} s (trajectory spans {t[0]:.3f}..{t[-1]:.3f} s); check that the "
            "relations belong to this log"
        )
    if n_matched < len(rs):
        logger.warning("%d of %d relations matched no scan", len(rs) - n_matched, len(rs))
    delta = se2.between(x[i1[ok]], x[i2[ok]])
    err = se2.compose(se2.inverse(rd[ok]), delta)
    trans = np.hypot(err[:, 0], err[:, 1])
    rot = np.degrees(np.abs(err[:, 2]))
    per = np.full((len(rs), 2), np.nan)
    per[ok, 0], per[ok, 1] = trans, rot
    summary = RelationErrors(
        n_relations=len(rs),
        n_matched=n_matched,
        trans_mean_m=float(trans.mean()),
        trans_std_m=float(trans.std()),
        rot_mean_deg=float(rot.mean()),
        rot_std_deg=float(rot.std()),
        trans_sq_mean_m2=float((trans**2).mean()),
        trans_sq_std_m2=float((trans**2).std()),
        rot_sq_mean_deg2=float((rot**2).mean()),
        rot_sq_std_deg2=float((rot**2).std()),
        trans_max_m=float(trans.max()),
        rot_max_deg=float(rot.max()),
    )
    return summary, per


@dataclass(frozen=True)
class PositionErrors:
    """Absolute trajectory error after a rigid 2D alignment (Horn 1987 / Umeyama 1991).

    Attributes:
        n_poses: poses compared.
        mean_m, rmse_m, max_m: position error statistics, metres.
        rot_mean_deg: mean absolute heading error after alignment, degrees.
        alignment: ``(3,)`` the SE(2) pose applied to the estimate, ``[x_m, y_m, theta_rad]``.
    """

    n_poses: int
    mean_m: float
    rmse_m: float
    max_m: float
    rot_mean_deg: float
    alignment: tuple[float, float, float]

    def as_dict(self) -> dict[str, object]:
        """Plain dict for JSON output."""
        return asdict(self)


def position_errors(estimate: ArrayLike, truth: ArrayLike, align: bool = True) -> PositionErrors:
    """Absolute position error of an estimated trajectory against ground truth.

    Args:
        estimate: ``(N, 3)`` estimated poses, world frame of the estimate.
        truth: ``(N, 3)`` true poses at the same instants, world frame of the truth.
        align: first find the rigid SE(2) transform that best maps the estimate onto the
            truth (least squares on positions; ``scipy.spatial.transform.Rotation.align_vectors``).

    Raises:
        EvaluationError: shapes differ or are empty.
    """
    est = np.asarray(estimate, dtype=np.float64)
    gt = np.asarray(truth, dtype=np.float64)
    if est.shape != gt.shape or est.ndim != 2 or est.shape[1] != 3 or len(est) == 0:
        raise EvaluationError(
            f"estimate {est.shape} and truth {gt.shape} must both be (N, 3) with N > 0"
        )
    alignment = np.zeros(3)
    if align and len(est) >= 2:
        mu_e, mu_g = est[:, :2].mean(0), gt[:, :2].mean(0)
        pad = np.zeros((len(est), 1))
        from scipy.spatial.transform import Rotation  # lazy: scipy is slow to import

        rot, _ = Rotation.align_vectors(
            np.hstack([gt[:, :2] - mu_g, pad]), np.hstack([est[:, :2] - mu_e, pad])
        )
        theta = float(rot.as_rotvec()[2])
        t_xy = mu_g - se2.rotation_matrix(theta) @ mu_e
        alignment = np.array([t_xy[0], t_xy[1], theta])
    aligned = se2.compose(alignment, est)
    d = np.hypot(*(aligned[:, :2] - gt[:, :2]).T)
    dth = np.degrees(np.abs(se2.wrap_angle(aligned[:, 2] - gt[:, 2])))
    return PositionErrors(
        n_poses=len(est),
        mean_m=float(d.mean()),
        rmse_m=float(np.sqrt((d**2).mean())),
        max_m=float(d.max()),
        rot_mean_deg=float(dth.mean()),
        alignment=(float(alignment[0]), float(alignment[1]), float(alignment[2])),
    )


def evo_ape_rpe(
    stamps_s: ArrayLike, estimate: ArrayLike, truth: ArrayLike, rpe_delta: int = 1
) -> dict[str, float]:
    """ATE (APE on translation, after SE(3) Umeyama alignment) and RPE through ``evo``.

    Requires the optional ``eval`` extra (``pip install iceg[eval]``); evo is GPL.

    Args:
        stamps_s: ``(N,)`` timestamps shared by both trajectories.
        estimate, truth: ``(N, 3)`` poses ``[x_m, y_m, theta_rad]``.
        rpe_delta: RPE pose-pair distance in frames.

    Returns:
        ``{"ape_rmse_m", "ape_mean_m", "rpe_trans_rmse_m"}``.

    Raises:
        EvaluationError: evo is not installed.
    """
    try:
        from evo.core import metrics, sync  # noqa: F401
        from evo.core.trajectory import PoseTrajectory3D
    except ImportError as exc:
        raise EvaluationError(
            "ATE/RPE need the optional evo package: pip install 'iceg[eval]'"
        ) from exc

    def to_traj(p: FloatArray) -> PoseTrajectory3D:
        xyz = np.column_stack([p[:, 0], p[:, 1], np.zeros(len(p))])
        quat_wxyz = np.column_stack(
            [np.cos(p[:, 2] / 2), np.zeros(len(p)), np.zeros(len(p)), np.sin(p[:, 2] / 2)]
        )
        return PoseTrajectory3D(xyz, quat_wxyz, np.asarray(stamps_s, dtype=np.float64))

    est = to_traj(np.asarray(estimate, dtype=np.float64))
    ref = to_traj(np.asarray(truth, dtype=np.float64))
    est.align(ref)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    rpe = metrics.RPE(metrics.PoseRelation.translation_part, delta=rpe_delta, all_pairs=False)
    rpe.process_data((ref, est))
    return {
        "ape_rmse_m": float(ape.get_statistic(metrics.StatisticsType.rmse)),
        "ape_mean_m": float(ape.get_statistic(metrics.StatisticsType.mean)),
        "rpe_trans_rmse_m": float(rpe.get_statistic(metrics.StatisticsType.rmse)),
    }
