"""The correlation fitness of paper eq. 1-3 as fixed in DESIGN.md step 7, vectorized over
hypotheses."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from iceg.matching._kernels import pair_nearest
from iceg.matching.geometry import FeatureGeometry, PolarProfile, rot

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def fimp(d_m: FloatArray, near: float, far: float, range_m: float) -> FloatArray:
    """Feature importance of paper eq. 3 as fixed in DESIGN step 7:
    ``fImp(d) = near / (1 + k d)`` with ``k`` such that ``fImp(range_m) = far``
    (defaults 0.65 and 0.1 at 20 m)."""
    k = (near / far - 1.0) / range_m
    return near / (1.0 + k * np.asarray(d_m, dtype=np.float64))


@dataclass(frozen=True, eq=False)
class Correlation:
    """Correlation of each hypothesis (paper eq. 1) and its feature pairing.

    Attributes:
        score: ``(H,)`` float64 correlation in ``[0, 1]``.
        dis, ang, count, acc: ``(H,)`` float64 the four terms of eq. 1.
        match: ``(H, K_new)`` int64 reference index paired with each new feature (-1: none).
        n_matched: ``(H,)`` int64 number of pairs.
        n_visible: ``(H,)`` int64 reference features visible from the hypothesised pose.
    """

    score: FloatArray
    dis: FloatArray
    ang: FloatArray
    count: FloatArray
    acc: FloatArray
    match: IntArray
    n_matched: IntArray
    n_visible: IntArray


def visible_reference(
    poses: FloatArray,
    gr: FeatureGeometry,
    profile: PolarProfile,
    range_max_m: float,
    occlusion_tolerance_m: float,
) -> NDArray[np.bool_]:
    """Which reference features the new scan could see from each hypothesised pose: inside
    the new scan's field of view and range, and not occluded (no pair of new beams around
    its bearing is shorter than its distance minus the tolerance). DESIGN "Feature map and
    time-validity"; used by the count term of eq. 1.

    Returns:
        ``(H, K_ref)`` bool.
    """
    h = poses.shape[0]
    if gr.n == 0 or profile.bearing.shape[0] == 0:
        return np.zeros((h, gr.n), dtype=bool)
    r = rot(poses[:, 2])  # (H, 2, 2)
    rel = gr.xy[None, :, :] - poses[:, None, :2]  # (H, K, 2)
    local = np.einsum("hba,hkb->hka", r, rel)  # R^T rel
    bearing = np.arctan2(local[..., 1], local[..., 0])
    dist = np.hypot(local[..., 0], local[..., 1])
    lo = profile.bearing[0] - profile.spacing
    hi = profile.bearing[-1] + profile.spacing
    rng = profile.lookup(bearing)
    occluded = rng < dist - occlusion_tolerance_m  # NaN -> False
    return (bearing >= lo) & (bearing <= hi) & (dist < range_max_m) & ~occluded


def correlate(
    poses: FloatArray,
    gn: FeatureGeometry,
    gr: FeatureGeometry,
    codes: IntArray,
    profile: PolarProfile,
    *,
    gate_distance_m: float,
    gate_angle_rad: float,
    fimp_near: float,
    fimp_far: float,
    fimp_range_m: float,
    range_max_m: float,
    occlusion_tolerance_m: float,
    weights: tuple[float, float, float, float],
    pairing_only: bool = False,
) -> Correlation:
    """Correlation of paper eq. 1-3 (DESIGN step 7) for ``H`` hypotheses at once.

    Under each hypothesis the new features move into the reference frame and each pairs
    with the nearest compatible reference feature inside the distance gate ``g_d`` and the
    angle gate ``g_a`` (one new feature per reference feature, the nearest wins). With
    ``w_i = fImp(d(nf_i)) fImp(d(of_i))`` (``d`` measured from each frame's origin):

    - ``dis = sum w_i (1 - dis_i / g_d) / sum w_i``
    - ``ang = sum w_i (1 - Angle_i / g_a) / sum w_i``
    - ``count = n_matched / min(n_new, n_ref_visible)``
    - ``acc = sum_matched w_i / sum_all_new fImp(d(nf))^2`` (eq. 2, clipped to 1)
    - ``correlation = (0.4 dis + 0.2 ang + 0.2 count + 0.6 acc) / 1.4``

    Args:
        poses: ``(H, 3)`` float64 hypothesised poses of the new scan in the reference frame.
        gn, gr: New and reference feature geometry.
        codes: ``(K_new, K_ref)`` pair codes from :func:`~iceg.matching.hypotheses.pair_codes`.
        profile: Polar profile of the new scan (visibility for ``count``).
        weights: ``(w_dis, w_ang, w_count, w_acc)`` of eq. 1.
        pairing_only: Only pair the features (``match``, ``n_matched``); the scores and
            ``n_visible`` are left at zero.

    Returns:
        A :class:`Correlation`.
    """
    h = poses.shape[0]
    kn, kr = gn.n, gr.n
    if pairing_only:
        n_visible = np.zeros(h, dtype=np.int64)
    else:
        visible = visible_reference(poses, gr, profile, range_max_m, occlusion_tolerance_m)
        n_visible = visible.sum(axis=1).astype(np.int64)
    zeros = np.zeros(h)
    if kn == 0 or kr == 0:
        return Correlation(
            zeros,
            zeros,
            zeros,
            zeros,
            zeros,
            np.full((h, kn), -1, dtype=np.int64),
            np.zeros(h, dtype=np.int64),
            n_visible,
        )
    match, dbest, a_best = pair_nearest(
        poses,
        gn.xy,
        gn.heading,
        gn.edge,
        gn.opening,
        gr.xy,
        gr.heading,
        gr.edge,
        gr.opening,
        codes,
        gate_distance_m,
        gate_angle_rad,
    )
    matched = match >= 0
    j = np.where(matched, match, 0)
    if pairing_only:
        zeros = np.zeros(h)
        return Correlation(
            zeros,
            zeros,
            zeros,
            zeros,
            zeros,
            match,
            matched.sum(axis=1).astype(np.int64),
            n_visible,
        )
    fn = fimp(gn.dist, fimp_near, fimp_far, fimp_range_m)  # (Kn,)
    fr = fimp(gr.dist, fimp_near, fimp_far, fimp_range_m)  # (Kr,)
    w = np.where(matched, fn[None, :] * fr[j], 0.0)
    sw = w.sum(axis=1)
    safe = np.where(sw > 0, sw, 1.0)
    d_term = np.where(matched, 1.0 - np.where(matched, dbest, 0.0) / gate_distance_m, 0.0)
    a_term = np.where(matched, 1.0 - np.where(matched, a_best, 0.0) / gate_angle_rad, 0.0)
    dis = np.where(sw > 0, (w * d_term).sum(axis=1) / safe, 0.0)
    ang = np.where(sw > 0, (w * a_term).sum(axis=1) / safe, 0.0)
    n_matched = matched.sum(axis=1).astype(np.int64)
    denom = np.maximum(1, np.minimum(kn, n_visible))
    count = np.clip(n_matched / denom, 0.0, 1.0)
    acc = np.clip(sw / np.sum(fn * fn), 0.0, 1.0)
    wd, wa, wc, wacc = weights
    score = (wd * dis + wa * ang + wc * count + wacc * acc) / (wd + wa + wc + wacc)
    return Correlation(score, dis, ang, count, acc, match, n_matched, n_visible)
