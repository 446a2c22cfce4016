"""SE(2) algebra on plain arrays, vectorized over leading dimensions.

A pose is ``(..., 3)`` float64 ``[x_m, y_m, theta_rad]``; composition ``a ∘ b`` applies
``b`` in the frame of ``a`` (the convention of gtsam ``Pose2.compose``). Angles are
wrapped to ``[-pi, pi)``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def wrap_angle(theta_rad: ArrayLike) -> FloatArray:
    """Wrap angles (any shape, radians) to ``[-pi, pi)``."""
    t = np.asarray(theta_rad, dtype=np.float64)
    return (t + np.pi) % (2.0 * np.pi) - np.pi


def _one_pose(a: object) -> bool:
    """Whether ``a`` is a single finite-heading ``(3,)`` float64 pose: the scalar path below
    serves it with ``math`` (libm's sin and cos, Python's float modulo: the same values as the
    numpy expressions, bit for bit, at a tenth of the call cost; ``math`` raises on an
    infinite angle where numpy gives NaN, so those take the numpy path)."""
    return (
        type(a) is np.ndarray and a.shape == (3,) and a.dtype == np.float64 and math.isfinite(a[2])
    )


def wrap_float(theta_rad: float) -> float:
    """:func:`wrap_angle` of one angle as a Python float (radians, to ``[-pi, pi)``): Python's
    float modulo gives numpy's bits at a tenth of the call cost."""
    return (theta_rad + math.pi) % (2.0 * math.pi) - math.pi


def compose(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """``a ∘ b`` for poses of shape ``(..., 3)`` (broadcasting); returns ``(..., 3)``."""
    if _one_pose(a) and _one_pose(b):
        ax, ay, at = a.tolist()  # type: ignore[union-attr]
        bx, by, bt = b.tolist()  # type: ignore[union-attr]
        c, s = math.cos(at), math.sin(at)
        return np.array([ax + c * bx - s * by, ay + s * bx + c * by, wrap_float(at + bt)])
    if _one_pose(a) and type(b) is np.ndarray and b.ndim == 2 and b.shape[1] == 3:
        # One pose and a batch (relative poses of many nodes): the same expressions with the
        # first pose's numbers as floats, without numpy's 0-d steps.
        ax, ay, at = a.tolist()  # type: ignore[union-attr]
        c, s = math.cos(at), math.sin(at)
        b = b.astype(np.float64, copy=False)
        out = np.empty(b.shape)
        out[:, 0] = ax + c * b[:, 0] - s * b[:, 1]
        out[:, 1] = ay + s * b[:, 0] + c * b[:, 1]
        out[:, 2] = (at + b[:, 2] + np.pi) % (2.0 * np.pi) - np.pi
        return out
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def inverse(a: ArrayLike) -> FloatArray:
    """Inverse pose ``a^-1`` for shape ``(..., 3)``."""
    if _one_pose(a):
        x, y, t = a.tolist()  # type: ignore[union-attr]
        c, s = math.cos(t), math.sin(t)
        return np.array([-(c * x + s * y), -(-s * x + c * y), wrap_float(-t)])
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -(c * a[..., 0] + s * a[..., 1])
    y = -(-s * a[..., 0] + c * a[..., 1])
    return np.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)


def between(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """Relative pose ``a^-1 ∘ b`` (``b`` expressed in the frame of ``a``), shape ``(..., 3)``."""
    return compose(inverse(a), b)


def accumulate(steps: ArrayLike) -> FloatArray:
    """Poses ``(n + 1, 3)`` float64 of a chain of ``n`` relative steps ``(n, 3)`` composed in
    order from the identity, ``[x_m, y_m, theta_rad]`` in the frame of the chain's first pose:
    row ``k`` is ``steps[0] ∘ ... ∘ steps[k-1]`` (row 0 the identity). Headings are summed,
    not wrapped."""
    d = np.asarray(steps, dtype=np.float64).reshape(-1, 3)
    theta = np.concatenate([[0.0], np.cumsum(d[:, 2])])
    c, s = np.cos(theta[:-1]), np.sin(theta[:-1])
    xy = np.zeros((d.shape[0] + 1, 2))
    xy[1:, 0] = np.cumsum(c * d[:, 0] - s * d[:, 1])
    xy[1:, 1] = np.cumsum(s * d[:, 0] + c * d[:, 1])
    return np.column_stack([xy, theta])


def transform_points(pose: ArrayLike, points_xy: ArrayLike) -> FloatArray:
    """Map points ``(K, 2)`` from the frame of ``pose`` (3,) into its parent frame."""
    p = np.asarray(pose, dtype=np.float64)
    pts = np.asarray(points_xy, dtype=np.float64)
    t = float(p[2])
    c, s = (math.cos(t), math.sin(t)) if math.isfinite(t) else (np.cos(t), np.sin(t))
    rot = np.array([[c, -s], [s, c]])
    return pts @ rot.T + p[:2]


def rotation_matrix(theta_rad: ArrayLike) -> FloatArray:
    """Rotation matrices ``(..., 2, 2)`` of angles ``(...)`` radians (``(2, 2)`` for a scalar)."""
    t = np.asarray(theta_rad, dtype=np.float64)
    c, s = np.cos(t), np.sin(t)
    out = np.empty((*t.shape, 2, 2))
    out[..., 0, 0] = c
    out[..., 0, 1] = -s
    out[..., 1, 0] = s
    out[..., 1, 1] = c
    return out


def adjoint(pose: ArrayLike) -> FloatArray:
    """Adjoint ``(..., 3, 3)`` of poses ``(..., 3)``, mapping a tangent vector
    ``(x, y, theta)`` in the pose's own frame to the parent frame:
    ``Ad = [[R, [y, -x]^T], [0, 0, 1]]``.

    Used to move a covariance between frames: ``cov_parent = Ad cov_child Ad^T``.
    """
    p = np.asarray(pose, dtype=np.float64)
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    out = np.zeros((*p.shape[:-1], 3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2] = c, -s, p[..., 1]
    out[..., 1, 0], out[..., 1, 1], out[..., 1, 2] = s, c, -p[..., 0]
    out[..., 2, 2] = 1.0
    return out
