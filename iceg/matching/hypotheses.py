"""Hierarchical candidate filter, transform hypotheses from feature pairs, and voting
(paper §III-C2 "Match process", §III-C3; docs/design.md steps 5-6)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from iceg.matching._kernels import (
    directed_poses,
    feasible_pair_indices,
    intersection_pair_poses,
    pair_code_matrix,
    pairs_of_kind,
    poses_within_bounds,
    segment_rotation_peak,
    vote_clusters,
)
from iceg.matching.config import MatchBounds
from iceg.matching.geometry import CORNER, INTERSECTION, FeatureGeometry, rot

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Pair codes: how a new feature may match a reference feature (paper §III-C2, type level).
INCOMPATIBLE, SAME_DIRECTED, CORNER_TO_EOW, EOW_TO_CORNER, INTERSECTIONS = 0, 1, 2, 3, 4


def _code_table(corner_eow: bool) -> IntArray:
    """``(3, 3)`` int64 pair code by (new kind, reference kind): Corner, EOW, Intersection."""
    table = np.array(
        [
            [SAME_DIRECTED, CORNER_TO_EOW if corner_eow else 0, 0],
            [EOW_TO_CORNER if corner_eow else 0, SAME_DIRECTED, 0],
            [0, 0, INTERSECTIONS],
        ],
        dtype=np.int64,
    )
    table.flags.writeable = False
    return table


#: The code tables without and with the Corner<->EOW exception.
_CODE_TABLES = {False: _code_table(False), True: _code_table(True)}


def pair_codes(
    gn: FeatureGeometry, gr: FeatureGeometry, corner_eow: bool, max_opening_diff_rad: float
) -> IntArray:
    """Type and opening-angle levels of the hierarchical filter for every (new, reference)
    feature pair (paper §III-C2: same type, or Corner<->EOW through one edge; the opening
    angles of two Corners or two Intersections may differ by a low threshold only).

    Returns:
        ``(K_new, K_ref)`` int64 pair codes (``INCOMPATIBLE`` where the pair is filtered out).
    """
    return pair_code_matrix(
        gn.kind,
        gn.opening,
        gr.kind,
        gr.opening,
        _CODE_TABLES[bool(corner_eow)],
        CORNER,
        INTERSECTIONS,
        float(max_opening_diff_rad),
    )


def rotation_chord(max_rotation_rad: float) -> float:
    """Largest displacement of a unit-distance point under a rotation of at most the bound."""
    return 2.0 * math.sin(min(max_rotation_rad, math.pi) / 2.0)


def feasible_pairs(
    gn: FeatureGeometry,
    gr: FeatureGeometry,
    codes: IntArray,
    prediction: FloatArray,
    bounds: MatchBounds,
    margin_m: float,
) -> tuple[IntArray, IntArray]:
    """Feasible-area level of the hierarchical filter (paper §III-C2: "only features placed
    in the feasible area should be checked").

    A new feature at ``p`` (new frame) can only be at ``prediction ∘ p`` moved by at most
    ``max_translation_m + |p| * chord(max_rotation)``; reference candidates inside that disc
    (plus ``margin_m``) are found by testing all pairs (squared distances).

    Returns:
        ``(Q,)`` new indices and ``(Q,)`` reference indices of pairs passing type, opening
        and feasible-area levels.
    """
    if gn.n == 0 or gr.n == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    if math.isinf(bounds.max_translation_m):
        i, j = np.nonzero(codes)
        return i.astype(np.int64), j.astype(np.int64)
    # R(theta) from libm's cosine and sine (numpy's, bit for bit), the product numpy's
    c, s = math.cos(prediction[2]), math.sin(prediction[2])
    r0 = np.array([[c, -s], [s, c]])
    # All (new, reference) pairs in one pass: a few dozen by a few hundred features, cheaper
    # than a KD-tree. Squared distances against squared radii, as cKDTree.query_ball_point
    # tests them, in row-major (sorted) order.
    return feasible_pair_indices(
        gn.xy @ r0.T,
        np.ascontiguousarray(prediction[:2], dtype=np.float64),
        gn.dist,
        float(bounds.max_translation_m),
        rotation_chord(bounds.max_rotation_rad),
        float(margin_m),
        np.ascontiguousarray(gr.xy, dtype=np.float64),
        np.ascontiguousarray(codes, dtype=np.int64),
    )


@dataclass(frozen=True, eq=False)
class Hypotheses:
    """Transform hypotheses: poses of the new scan in the reference frame.

    Attributes:
        poses: ``(N, 3)`` float64 ``[x_m, y_m, theta_rad]``.
        n_pairs: Number of candidate feature pairs that survived the filter.
    """

    poses: FloatArray
    n_pairs: int


def directed_hypotheses(
    gn: FeatureGeometry,
    gr: FeatureGeometry,
    i: IntArray,
    j: IntArray,
    codes: IntArray,
) -> FloatArray:
    """One SE(2) hypothesis per directed pair (docs/design.md step 6; paper §III-C3: "vector and the
    angle difference between them show the translation (dx, dy) and rotation (dtheta)").

    Corner<->Corner and EOW<->EOW pairs align the headings (bisector / wall direction); a
    Corner<->EOW pair gives one hypothesis per Corner edge. ``t = xy_ref - R(theta) xy_new``.

    Returns:
        ``(N, 3)`` float64 poses (unfiltered).
    """
    return directed_poses(
        np.ascontiguousarray(i, dtype=np.int64),
        np.ascontiguousarray(j, dtype=np.int64),
        np.ascontiguousarray(codes, dtype=np.int64),
        gn.heading,
        gn.edge,
        gn.xy,
        gr.heading,
        gr.edge,
        gr.xy,
        SAME_DIRECTED,
        CORNER_TO_EOW,
        EOW_TO_CORNER,
    )


def intersection_hypotheses(
    gn: FeatureGeometry,
    gr: FeatureGeometry,
    i: IntArray,
    j: IntArray,
    prediction: FloatArray,
    tolerance_m: float,
    min_baseline_m: float,
    max_pairs: int,
) -> FloatArray:
    """Hypotheses from two Intersection pairs each (docs/design.md step 6: Intersections have no
    direction, two pairs fix a transform).

    Pairs ``(i1 -> j1)`` and ``(i2 -> j2)`` combine when ``|n_i1 n_i2|`` equals
    ``|r_j1 r_j2|`` within ``tolerance_m`` and exceeds ``min_baseline_m``; the rotation aligns
    the two baselines and the translation is the mean of both pairs'.

    Returns:
        ``(N, 3)`` float64 poses (unfiltered).
    """
    i, j = pairs_of_kind(i, j, gn.kind, gr.kind, INTERSECTION)
    if i.shape[0] < 2:
        return np.zeros((0, 3))
    if i.shape[0] > max_pairs:
        # Keep the pairs whose implied displacement is closest to the prediction's.
        r0 = rot(prediction[2])
        pred = gn.xy[i] @ r0.T + prediction[:2]
        d = np.hypot(*(pred - gr.xy[j]).T)
        keep = np.argsort(d, kind="stable")[:max_pairs]
        i, j = i[keep], j[keep]
    return intersection_pair_poses(
        np.ascontiguousarray(i, dtype=np.int64),
        np.ascontiguousarray(j, dtype=np.int64),
        gn.xy,
        gr.xy,
        tolerance_m,
        min_baseline_m,
    )


def generate_hypotheses(
    gn: FeatureGeometry,
    gr: FeatureGeometry,
    codes: IntArray,
    prediction: FloatArray,
    bounds: MatchBounds,
    *,
    margin_m: float,
    direction_tolerance_rad: float,
    intersection_tolerance_m: float,
    intersection_min_baseline_m: float,
    max_intersection_pairs: int,
) -> Hypotheses:
    """Steps 5-6 of docs/design.md up to voting: filter candidates hierarchically (type, feasible
    area, opening angle; direction against the predicted rotation) and build SE(2)
    hypotheses from the survivors.

    Returns:
        The :class:`Hypotheses` inside the bounds (plus tolerances).
    """
    i, j = feasible_pairs(gn, gr, codes, prediction, bounds, margin_m)
    directed = directed_hypotheses(gn, gr, i, j, codes)
    inter = intersection_hypotheses(
        gn,
        gr,
        i,
        j,
        prediction,
        intersection_tolerance_m,
        intersection_min_baseline_m,
        max_intersection_pairs,
    )
    max_rotation_rad = bounds.max_rotation_rad + direction_tolerance_rad
    poses = poses_within_bounds(
        np.ascontiguousarray(directed, dtype=np.float64),
        np.ascontiguousarray(inter, dtype=np.float64),
        np.ascontiguousarray(prediction, dtype=np.float64),
        math.inf if bounds.rotation_unbounded else max_rotation_rad,
        bounds.max_translation_m + margin_m,
    )
    return Hypotheses(poses, int(i.shape[0]))


@dataclass(frozen=True, eq=False)
class Clusters:
    """Voted hypothesis clusters, best first.

    Attributes:
        poses: ``(C, 3)`` float64 cluster centres (mean of member hypotheses).
        votes: ``(C,)`` int64 number of hypotheses in each cluster's 3x3x3 cell
            neighbourhood.
    """

    poses: FloatArray
    votes: IntArray


def vote(poses: FloatArray, cell_m: float, cell_rad: float, max_clusters: int) -> Clusters:
    """Cluster hypotheses on a grid in ``(x, y, theta)`` and return the most-voted local
    maxima first (paper §III-C3: "we start it from the conversion with the most count").

    Each hypothesis votes for its cell; a cell's score is the number of votes in its 3x3x3
    neighbourhood (theta periodic); clusters are cells whose score is a local maximum, and
    their centre is the mean of the hypotheses in the neighbourhood (theta about the cell).

    Args:
        poses: ``(N, 3)`` float64 hypotheses.
        cell_m: Cell size in x and y, metres.
        cell_rad: Cell size in theta, radians (rounded so that it divides 2 pi).
        max_clusters: Most clusters returned.
    """
    if poses.shape[0] == 0:
        return Clusters(np.zeros((0, 3)), np.zeros(0, dtype=np.int64))
    n_t = max(1, round(2.0 * math.pi / cell_rad))
    pts = np.ascontiguousarray(poses, dtype=np.float64)
    centres, votes = vote_clusters(pts, cell_m, n_t, 2.0 * math.pi / n_t, max_clusters)
    return Clusters(centres, votes)


def segment_rotation(
    new_lines: FloatArray,
    new_lengths: FloatArray,
    ref_lines: FloatArray,
    ref_lengths: FloatArray,
    theta0: float,
    max_dev_rad: float,
    kernel_rad: float,
    min_support_m: float,
) -> float | None:
    """Rotation that best aligns the new scan's segment directions with the reference's,
    near ``theta0`` (a weighted kernel-density peak over all segment pairs; lines are
    undirected, so differences are taken modulo pi). Used to start the refinement from the
    prediction with its rotation already right, where features give no hypothesis.

    Args:
        new_lines, ref_lines: ``(M, 2)`` Hessian lines ``(alpha_rad, rho_m)``.
        new_lengths, ref_lengths: ``(M,)`` segment lengths, metres (pair weight: the shorter).
        theta0: Predicted rotation, radians.
        max_dev_rad: Largest admissible deviation from ``theta0``.
        kernel_rad: Standard deviation of the Gaussian kernel.
        min_support_m: Least weight (metres of agreeing segment length) at the peak.

    Returns:
        The rotation in radians, or ``None`` when no peak has enough support.
    """
    if new_lines.shape[0] == 0 or ref_lines.shape[0] == 0:
        return None
    found, rotation = segment_rotation_peak(
        np.ascontiguousarray(new_lines, dtype=np.float64),
        np.ascontiguousarray(new_lengths, dtype=np.float64),
        np.ascontiguousarray(ref_lines, dtype=np.float64),
        np.ascontiguousarray(ref_lengths, dtype=np.float64),
        float(theta0),
        float(max_dev_rad),
        float(kernel_rad),
        float(min_support_m),
    )
    return float(rotation) if found else None
