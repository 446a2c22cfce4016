"""Configuration of the pose-graph back-end: iSAM2 / batch settings and the odometry noise model.

Units are in the field names. Angles are given in degrees here (the edge of the library) and
converted to radians once, by the properties ending in ``_rad``.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class OdometryNoiseConfig(BaseModel):
    """Parameters of the odometry noise model of :func:`graph.odometry_covariance`.

    The standard deviations grow linearly with the distance and rotation travelled between
    two nodes, on top of a floor that keeps the covariance positive definite for a robot that
    stands still::

        sigma_xy_m      = sigma_xy_base_m + sigma_xy_per_distance_m_per_m * dist_m
        sigma_theta_rad = sigma_theta_base + sigma_theta_per_rotation * |dtheta|
                          + sigma_theta_per_distance * dist_m

    This is the linear-in-motion form of the odometry motion model of Thrun, Burgard & Fox,
    *Probabilistic Robotics* (2005), §5.4 (parameters alpha_1..alpha_4), with additive floors.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    sigma_xy_base_m: float = Field(
        default=0.01,
        gt=0.0,
        description="Floor of the translation standard deviation per step (m); keeps the "
        "covariance positive definite at zero motion (Thrun et al. 2005, §5.4, with a floor).",
    )
    sigma_xy_per_distance_m_per_m: float = Field(
        default=0.02,
        ge=0.0,
        description="Growth of the translation standard deviation with the distance travelled "
        "(m per m); alpha_3 of the odometry motion model (Thrun et al. 2005, §5.4).",
    )
    sigma_theta_base_deg: float = Field(
        default=0.5,
        gt=0.0,
        description="Floor of the heading standard deviation per step (deg).",
    )
    sigma_theta_per_rotation_deg_per_deg: float = Field(
        default=0.05,
        ge=0.0,
        description="Growth of the heading standard deviation with the rotation travelled "
        "(deg per deg); alpha_1 of the odometry motion model (Thrun et al. 2005, §5.4).",
    )
    sigma_theta_per_distance_deg_per_m: float = Field(
        default=0.5,
        ge=0.0,
        description="Growth of the heading standard deviation with the distance travelled "
        "(deg per m); alpha_2 of the odometry motion model (Thrun et al. 2005, §5.4).",
    )

    @property
    def sigma_theta_base_rad(self) -> float:
        """``sigma_theta_base_deg`` in radians."""
        return math.radians(self.sigma_theta_base_deg)

    @property
    def sigma_theta_per_distance_rad_per_m(self) -> float:
        """``sigma_theta_per_distance_deg_per_m`` in radians per metre."""
        return math.radians(self.sigma_theta_per_distance_deg_per_m)


class GraphConfig(BaseModel):
    """Settings of :class:`graph.PoseGraph`: iSAM2, batch Levenberg–Marquardt, first-node prior.

    iSAM2 is Kaess et al., "iSAM2: Incremental smoothing and mapping using the Bayes tree",
    IJRR 31(2), 2012; the relinearization threshold and skip are its §5 (fluid
    relinearization). The defaults were chosen on the INTEL and M3500b graphs of
    ``../shared/data/g2o``: with them, and 3 * relinearize_skip extra update() calls after the
    last node, the incremental estimate matches the batch optimum within 2.3 mm and 0.022 deg
    per node (see ``tests/graph/test_g2o_datasets.py``; 0.26 mm and 0.0026 deg with
    ``relinearize_threshold_xy_m=None``, at 1.3 times the feed time on M3500b).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    prior_sigma_xy_m: float = Field(
        default=1e-3,
        gt=0.0,
        description="Standard deviation of the prior that anchors the first node (m); it "
        "fixes the gauge freedom of a pose graph.",
    )
    prior_sigma_theta_deg: float = Field(
        default=0.01,
        gt=0.0,
        description="Standard deviation of the heading of the first-node prior (deg).",
    )
    relinearize_threshold: float = Field(
        default=1e-3,
        gt=0.0,
        description="iSAM2 relinearizes a node when a component of its accumulated update "
        "exceeds this (m for x, y and rad for theta; Kaess et al. 2012, §5, Alg. 6). gtsam's "
        "default 0.1 leaves the M3500b estimate 7 cm from the batch optimum, 0.01 leaves 1.5 to "
        "2.4 cm, 1e-3 leaves 0.3 mm (with relinearize_threshold_xy_m=None).",
    )
    relinearize_threshold_xy_m: float | None = Field(
        default=0.01,
        gt=0.0,
        description="The threshold of the x and y components alone (m); None: "
        "relinearize_threshold. A between factor of two poses is linear in their translations "
        "once their headings are fixed (its Jacobians depend on the headings and on the "
        "relative translation), so a stale translation costs a second-order error (the "
        "translation update times a heading update), while a stale heading turns the "
        "Jacobians: translations can wait longer. M3500b: 2.3 mm from the batch optimum "
        "instead of 0.26 mm, 1.3 times faster; MIT CSAIL driven back and forth (scans "
        "2000-6000): iSAM2 relinearizes a third as many nodes, its updates take half the time.",
    )
    relinearize_skip: int = Field(
        default=10,
        ge=1,
        description="Check for relinearization every this many update() calls (Kaess et al. "
        "2012, §5; gtsam's default). On M3500b, 10 instead of 1 makes the node-by-node run 3 "
        "times faster; the newest nodes then need a few multiples of it in extra update() "
        "calls (or optimize_batch) to reach the optimum.",
    )
    factorization: Literal["auto", "qr", "cholesky"] = Field(
        default="auto",
        description="Elimination of iSAM2 and of the batch linear solver. Cholesky is about "
        "twice as fast (10,000-node Manhattan world: 19.5 s vs 43 s at 5000 nodes); QR survives "
        "ill-conditioned covariances (INTEL has information matrices with condition number "
        "2.4e11, on which gtsam's Cholesky reports an indeterminant system at node 11). 'auto' "
        "starts with Cholesky and, at the first indeterminant system, rebuilds iSAM2 with QR "
        "from its linearization point and stays on QR.",
    )
    batch_relative_error_tol: float = Field(
        default=1e-10,
        gt=0.0,
        description="Levenberg–Marquardt stops when the error decreases by less than this "
        "fraction. Tight on purpose: pose-graph costs are flat along long loops, and gtsam's "
        "default 1e-5 stops centimetres short of the optimum on M3500b.",
    )
    correction_relative_error_tol: float = Field(
        default=1e-5,
        gt=0.0,
        description="Relative error tolerance of a mid-run batch solve after a large "
        "correction (a group of global loop closures; ``PoseGraph.optimize_batch(correction="
        "True)``). It only has to bring the estimate into iSAM2's basin: iSAM2 relinearizes "
        "from there with every update, and the final refinement uses "
        "``batch_relative_error_tol``. gtsam's default; on CSAIL driven back and forth (7000 "
        "nodes) 1e-10 took 100 iterations (10 s) to move the poses at most 6 cm past the 13th.",
    )
    final_closure_consistency_chi2: float | None = Field(
        default=16.27,
        gt=0.0,
        description="A final refinement without loop-closure kernels "
        "(``PoseGraph.optimize_batch(loop_closure_kernels=False)``) keeps the kernel of a robust "
        "loop closure the rest of the graph contradicts: its residual at the current estimate, "
        "under its own covariance plus the relative covariance of its two nodes without it "
        "(leave-one-out, from the joint marginal), beyond this chi-square (3 dof; 16.27 is "
        "99.9 %). A closure accepted against a drifted estimate that a later correction "
        "disproved then cannot bend the final map (MIT CSAIL driven back and forth: one 7.3 m "
        "off). None: every loop closure Gaussian.",
    )
    batch_diagonal_damping: bool = Field(
        default=True,
        description="Scale the Levenberg–Marquardt damping by the diagonal of the Hessian "
        "(Marquardt 1963) instead of the identity; needed when covariances span many orders "
        "of magnitude, as on INTEL.",
    )

    @property
    def prior_sigma_theta_rad(self) -> float:
        """``prior_sigma_theta_deg`` in radians."""
        return math.radians(self.prior_sigma_theta_deg)
