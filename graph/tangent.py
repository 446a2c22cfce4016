"""The tangent space the graph's factors and marginals live in."""

from __future__ import annotations

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from iceg_common.errors import GraphError


def local_coordinates(at: ArrayLike, to: ArrayLike) -> NDArray[np.float64]:
    """``Log(at⁻¹ ∘ to)``: the tangent vector at ``at`` that reaches ``to`` (gtsam's
    ``Pose2.localCoordinates``, the SE(2) logarithm). It is the error of a between-factor
    measuring ``at`` when the true relative pose is ``to``, and the perturbation ``xi`` of a
    marginal (``pose = estimate ∘ Exp(xi)``, :meth:`graph.PoseGraph.marginal_covariance`).

    Args:
        at: ``(3,)`` or ``(k, 3)`` float poses ``[x_m, y_m, theta_rad]``.
        to: The same shape, in the same frame.

    Returns:
        ``(3,)`` or ``(k, 3)`` float64 ``[x_m, y_m, theta_rad]`` (the shape of ``at``).

    Raises:
        GraphError: the shapes differ or are not ``(3,)`` / ``(k, 3)``.
    """
    a = np.asarray(at, dtype=np.float64)
    b = np.asarray(to, dtype=np.float64)
    if a.shape != b.shape or a.shape[-1:] != (3,) or a.ndim > 2:
        raise GraphError(f"local_coordinates: poses {a.shape} and {b.shape} must be (3,) or (k, 3)")
    rows = [
        gtsam.Pose2(*p).localCoordinates(gtsam.Pose2(*q))
        for p, q in zip(a.reshape(-1, 3).tolist(), b.reshape(-1, 3).tolist(), strict=True)
    ]
    return np.asarray(rows, dtype=np.float64).reshape(a.shape)
