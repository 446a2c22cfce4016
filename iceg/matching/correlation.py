"""The correlation fitness of paper eq. 1-3 as fixed in docs/design.md step 7, vectorized over
hypotheses."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from iceg.matching._kernels import (
    FeaturePairing,
    correlation_scores,
    pair_nearest,
    visible_counts,
)
from iceg.matching.config import CorrelationConfig
from iceg.matching.geometry import MAX_GAP_BEAMS, FeatureGeometry, PolarProfile

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def fimp(d_m: FloatArray, near: float, far: float, range_m: float) -> FloatArray:
    """Feature importance of paper eq. 3 as fixed in docs/design.md step 7:
    ``fImp(d) = near / (1 + k d)`` with ``k`` such that ``fImp(range_m) = far``
    (defaults 0.65 and 0.1 at 20 m)."""
    return near / (1.0 + fimp_slope(near, far, range_m) * np.asarray(d_m, dtype=np.float64))


def fimp_slope(near: float, far: float, range_m: float) -> float:
    """``k`` of :func:`fimp` (1/m): ``fImp(range_m) = near / (1 + k range_m) = far``."""
    return (near / far - 1.0) / range_m


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


@dataclass(frozen=True)
class CorrelationSettings:
    """Numbers of the correlation in internal units (metres, radians).

    Attributes:
        gate_distance_m: ``g_d`` of eq. 1.
        gate_angle_rad: ``g_a`` of eq. 1.
        fimp_near, fimp_far, fimp_range_m: ``fImp`` of eq. 3 (see :func:`fimp`).
        range_max_m: The new scan's reliable range (visibility for ``count``).
        occlusion_tolerance_m: Occlusion allowance of the visibility test.
        weights: ``(w_dis, w_ang, w_count, w_acc)`` of eq. 1.
    """

    gate_distance_m: float
    gate_angle_rad: float
    fimp_near: float
    fimp_far: float
    fimp_range_m: float
    range_max_m: float
    occlusion_tolerance_m: float
    weights: tuple[float, float, float, float]

    @classmethod
    def from_config(cls, c: CorrelationConfig, range_max_m: float) -> CorrelationSettings:
        """Settings from the config section and the new scan's range (``fimp_range_m``
        defaults to it)."""
        return cls(
            gate_distance_m=c.gate_distance_m,
            gate_angle_rad=math.radians(c.gate_angle_deg),
            fimp_near=c.fimp_near,
            fimp_far=c.fimp_far,
            fimp_range_m=c.fimp_range_m or range_max_m,
            range_max_m=range_max_m,
            occlusion_tolerance_m=c.occlusion_tolerance_m,
            weights=(c.weight_dis, c.weight_ang, c.weight_count, c.weight_acc),
        )


def _empty(h: int, kn: int, n_visible: IntArray) -> Correlation:
    zeros = np.zeros(h)
    none = np.full((h, kn), -1, dtype=np.int64)
    return Correlation(zeros, zeros, zeros, zeros, zeros, none, np.zeros(h, np.int64), n_visible)


def feature_pairing(
    gn: FeatureGeometry, gr: FeatureGeometry, codes: IntArray, settings: CorrelationSettings
) -> FeaturePairing:
    """The arguments of :func:`pair_features` after the poses, as the kernels take them."""
    return FeaturePairing(
        gn.xy,
        gn.heading,
        gn.edge,
        gn.opening,
        gr.xy,
        gr.heading,
        gr.edge,
        gr.opening,
        codes,
        settings.gate_distance_m,
        settings.gate_angle_rad,
    )


def pair_features(
    poses: FloatArray,
    gn: FeatureGeometry,
    gr: FeatureGeometry,
    codes: IntArray,
    settings: CorrelationSettings,
) -> tuple[IntArray, FloatArray, FloatArray]:
    """The correlation's feature pairing (docs/design.md step 7) under ``H`` hypotheses: each new
    feature pairs with the nearest compatible reference feature inside ``g_d`` and ``g_a``
    (one new feature per reference feature, the nearest wins).

    Returns:
        ``match`` ``(H, K_new)`` int64 reference index (-1: none), ``dist`` (m) and ``angle``
        (rad) ``(H, K_new)`` float64 of each pair (NaN where unpaired).
    """
    return pair_nearest(poses, *feature_pairing(gn, gr, codes, settings))


def correlate(
    poses: FloatArray,
    gn: FeatureGeometry,
    gr: FeatureGeometry,
    codes: IntArray,
    profile: PolarProfile,
    settings: CorrelationSettings,
    pairing_only: bool = False,
) -> Correlation:
    """Correlation of paper eq. 1-3 (docs/design.md step 7) for ``H`` hypotheses at once.

    Under each hypothesis the new features move into the reference frame and pair as in
    :func:`pair_features`. With ``w_i = fImp(d(nf_i)) fImp(d(of_i))`` (``d`` measured from
    each frame's origin):

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
        settings: Gates, ``fImp`` and the weights of eq. 1.
        pairing_only: Only pair the features (``match``, ``n_matched``); the scores and
            ``n_visible`` are left at zero.

    Returns:
        A :class:`Correlation`.
    """
    h = poses.shape[0]
    st = settings
    if not pairing_only and gn.n > 0 and gr.n > 0:
        # Visible: inside the new scan's field of view and range and not occluded (no return
        # near its bearing shorter than its distance minus the tolerance); docs/design.md
        # "Feature map and time-validity".
        return Correlation(
            *correlation_scores(
                poses,
                gn.xy,
                gn.heading,
                gn.edge,
                gn.opening,
                gn.dist,
                gr.xy,
                gr.heading,
                gr.edge,
                gr.opening,
                gr.dist,
                codes,
                *_visibility_args(profile, st),
                st.gate_distance_m,
                st.gate_angle_rad,
                st.fimp_near,
                fimp_slope(st.fimp_near, st.fimp_far, st.fimp_range_m),
                st.weights,
            )
        )
    if pairing_only or gr.n == 0 or profile.bearing.shape[0] == 0:
        n_visible = np.zeros(h, dtype=np.int64)
    else:
        n_visible = visible_counts(poses, gr.xy, *_visibility_args(profile, st))
    if gn.n == 0 or gr.n == 0:
        return _empty(h, gn.n, n_visible)
    match, _, _ = pair_features(poses, gn, gr, codes, settings)
    out = _empty(h, gn.n, n_visible)
    n_matched = (match >= 0).sum(axis=1).astype(np.int64)
    return Correlation(out.score, out.dis, out.ang, out.count, out.acc, match, n_matched, n_visible)


def _visibility_args(
    profile: PolarProfile, settings: CorrelationSettings
) -> tuple[FloatArray, FloatArray, float, float, float, float]:
    """The new scan's arguments of :func:`~iceg.matching._kernels.visible_counts`: its
    bearings and ranges, beam spacing, the largest gap to a return that still judges
    occlusion (radians), its reliable range and the occlusion tolerance (metres)."""
    return (
        profile.bearing,
        profile.range,
        profile.spacing,
        MAX_GAP_BEAMS * profile.spacing,
        settings.range_max_m,
        settings.occlusion_tolerance_m,
    )


@dataclass(frozen=True, eq=False)
class CorrelationModel:
    """The correlation of one match: both scans' feature geometry, their pair codes, the
    new scan's polar profile and the settings (paper eq. 1-3, docs/design.md step 7).

    Attributes:
        new_geom, ref_geom: New (robot frame) and reference feature geometry.
        codes: ``(K_new, K_ref)`` int64 pair codes.
        profile: Polar profile of the new scan.
        settings: Correlation settings.
    """

    new_geom: FeatureGeometry
    ref_geom: FeatureGeometry
    codes: IntArray
    profile: PolarProfile
    settings: CorrelationSettings

    def score(self, poses: FloatArray) -> Correlation:
        """:func:`correlate` at ``(H, 3)`` poses of the new scan in the reference frame."""
        return correlate(
            poses, self.new_geom, self.ref_geom, self.codes, self.profile, self.settings
        )

    @functools.cached_property
    def feature_pairing(self) -> FeaturePairing:
        """:func:`feature_pairing` of this match, for the refinement's kernel."""
        return feature_pairing(self.new_geom, self.ref_geom, self.codes, self.settings)
