"""Scan segmentation: adaptive breakpoints, then split-and-merge inside each cluster.

docs/design.md "ICE matching, step by step", steps 2-3; paper §III-C1. The breakpoint test, the
recursive end-point fit and the merge run in numba-compiled loops (a few dozen segments per
scan, each needing a pass over its points).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from iceg_common.numba_loading import njit

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

# Breakpoint threshold: this many range standard deviations (Borges & Aldon 2004, eq. 8).
BREAKPOINT_SIGMAS = 3.0
# A total-least-squares line needs at least this many points to have a residual.
MIN_LINE_POINTS = 3
# Boundary refinement moves a boundary between two pieces by at most this many points.
BOUNDARY_SHIFT_POINTS = 2
# At most this many refine-then-merge passes (each joins every mergeable neighbour once).
MAX_MERGE_PASSES = 4
# A chord shorter than this (metres) has no direction: the split uses point distances.
DEGENERATE_CHORD_M = 1e-12


@njit(cache=True, nogil=True, error_model="numpy")
def breakpoints(
    points_xy: FloatArray,
    ranges_m: FloatArray,
    bearings_rad: FloatArray,
    beam_index: IntArray,
    sigma_range_m: float,
    lambda_rad: float,
) -> IntArray:
    """Cluster boundaries of a scan by the adaptive breakpoint detector.

    Two consecutive valid points ``p_{n-1}, p_n`` belong to different clusters when
    ``|p_n - p_{n-1}| > r_{n-1} sin(dphi) / sin(lambda - dphi) + 3 sigma_r`` (Borges & Aldon
    2004, "Line extraction in 2D range images for mobile robotics", eq. 8), or when an invalid
    beam lies between them (their beam indices are not consecutive), or when
    ``dphi >= lambda``.

    Args:
        points_xy: ``(P, 2)`` float64 valid beam endpoints, metres (any rigid frame).
        ranges_m: ``(P,)`` float64 their ranges, metres.
        bearings_rad: ``(P,)`` float64 their beam bearings, radians, increasing.
        beam_index: ``(P,)`` int64 their indices in the full scan.
        sigma_range_m: Range noise standard deviation, metres.
        lambda_rad: Borges & Aldon's lambda, radians.

    Returns:
        ``(C + 1,)`` int64 cluster boundaries: cluster ``c`` is ``[b[c], b[c + 1])`` in point
        index; ``[0]`` for an empty scan.
    """
    n = points_xy.shape[0]
    out = np.empty(n + 2, dtype=np.int64)
    out[0] = 0
    if n == 0:
        return out[:1]
    noise = BREAKPOINT_SIGMAS * sigma_range_m
    k = 1
    for i in range(1, n):
        dphi = bearings_rad[i] - bearings_rad[i - 1]
        jump = math.hypot(
            points_xy[i, 0] - points_xy[i - 1, 0], points_xy[i, 1] - points_xy[i - 1, 1]
        )
        d_max = ranges_m[i - 1] * math.sin(dphi) / math.sin(lambda_rad - dphi) + noise
        if beam_index[i] - beam_index[i - 1] != 1 or dphi >= lambda_rad or jump > d_max:
            out[k] = i
            k += 1
    out[k] = n
    return out[: k + 1]


@njit(cache=True)
def _scatter(
    x: FloatArray, y: FloatArray, s: int, e: int
) -> tuple[float, float, float, float, float]:
    """Centroid and scatter ``(mx, my, sxx, syy, sxy)`` of points ``[s, e)``."""
    m = e - s
    mx = 0.0
    my = 0.0
    for i in range(s, e):
        mx += x[i]
        my += y[i]
    mx /= m
    my /= m
    sxx = 0.0
    syy = 0.0
    sxy = 0.0
    for i in range(s, e):
        dx = x[i] - mx
        dy = y[i] - my
        sxx += dx * dx
        syy += dy * dy
        sxy += dx * dy
    return mx, my, sxx, syy, sxy


@njit(cache=True)
def _tls(x: FloatArray, y: FloatArray, s: int, e: int) -> tuple[float, float, float, float]:
    """Unweighted total-least-squares line of points ``[s, e)``.

    Returns ``(nx, ny, c, max_abs_residual)`` with the line ``nx x + ny y = c``.
    """
    mx, my, sxx, syy, sxy = _scatter(x, y, s, e)
    alpha = 0.5 * math.atan2(-2.0 * sxy, syy - sxx)
    nx = math.cos(alpha)
    ny = math.sin(alpha)
    c = nx * mx + ny * my
    worst = 0.0
    for i in range(s, e):
        d = abs(nx * x[i] + ny * y[i] - c)
        if d > worst:
            worst = d
    return nx, ny, c, worst


@njit(cache=True)
def _sse(x: FloatArray, y: FloatArray, s: int, e: int) -> float:
    """Sum of squared total-least-squares residuals of points ``[s, e)``: the smallest
    eigenvalue of their scatter matrix, m²; 0 for fewer than ``MIN_LINE_POINTS`` (3) points."""
    m = e - s
    if m < MIN_LINE_POINTS:
        return 0.0
    _, _, sxx, syy, sxy = _scatter(x, y, s, e)
    # Smallest eigenvalue of the scatter matrix.
    half_tr = 0.5 * (sxx + syy)
    disc = math.sqrt(max(0.25 * (sxx - syy) ** 2 + sxy * sxy, 0.0))
    return max(half_tr - disc, 0.0)


@njit(cache=True)
def _refine_boundaries(
    x: FloatArray,
    y: FloatArray,
    starts: IntArray,
    stops: IntArray,
    same: NDArray[np.bool_],
    n_pieces: int,
) -> None:
    """Move each boundary between adjacent pieces of one cluster by up to
    ``BOUNDARY_SHIFT_POINTS`` points to where the two lines' summed squared residuals are
    smallest (in place)."""
    for i in range(n_pieces - 1):
        if not same[i] or stops[i] != starts[i + 1]:
            continue
        s = starts[i]
        e = stops[i + 1]
        b0 = stops[i]
        best_b = b0
        best = _sse(x, y, s, b0) + _sse(x, y, b0, e)
        for db in range(-BOUNDARY_SHIFT_POINTS, BOUNDARY_SHIFT_POINTS + 1):
            b = b0 + db
            if db == 0 or b - s < MIN_LINE_POINTS or e - b < MIN_LINE_POINTS:
                continue
            cost = _sse(x, y, s, b) + _sse(x, y, b, e)
            if cost < best:
                best = cost
                best_b = b
        stops[i] = best_b
        starts[i + 1] = best_b


@njit(cache=True)
def farthest_from_chord(x: FloatArray, y: FloatArray, s: int, e: int, threshold_m: float) -> int:
    """Index of the point of ``[s, e)`` farthest from the chord of its first and last points
    (from the first point when the chord is degenerate) if that distance exceeds
    ``threshold_m``, else -1 (the end-point fit of Nguyen et al. 2005, Alg. 1)."""
    k_best = -1
    if e - s < MIN_LINE_POINTS:
        return k_best
    x0 = x[s]
    y0 = y[s]
    dx = x[e - 1] - x0
    dy = y[e - 1] - y0
    norm = math.sqrt(dx * dx + dy * dy)
    d_best = threshold_m
    for i in range(s + 1, e - 1):
        if norm > DEGENERATE_CHORD_M:
            d = abs((x[i] - x0) * dy - (y[i] - y0) * dx) / norm
        else:
            d = math.sqrt((x[i] - x0) ** 2 + (y[i] - y0) ** 2)
        if d > d_best:
            d_best = d
            k_best = i
    return k_best


@njit(cache=True)
def _split_clusters(
    x: FloatArray,
    y: FloatArray,
    bounds: IntArray,
    split_distance_m: float,
    starts: IntArray,
    stops: IntArray,
    owner: IntArray,
) -> int:
    """Recursive end-point fit of every cluster, run with an explicit stack: fills
    ``starts``, ``stops`` and ``owner`` (cluster) of the pieces in point order and returns
    their number."""
    stack_s = np.empty(x.shape[0] + 1, dtype=np.int64)
    stack_e = np.empty(x.shape[0] + 1, dtype=np.int64)
    n_pieces = 0
    for c in range(bounds.shape[0] - 1):
        if bounds[c + 1] <= bounds[c]:
            continue
        # Depth-first with the right half pushed first, so pieces come out in point order.
        stack_s[0] = bounds[c]
        stack_e[0] = bounds[c + 1]
        top = 1
        while top > 0:
            top -= 1
            s = stack_s[top]
            e = stack_e[top]
            k_best = farthest_from_chord(x, y, s, e, split_distance_m)
            if k_best < 0:
                starts[n_pieces] = s
                stops[n_pieces] = e
                owner[n_pieces] = c
                n_pieces += 1
            else:
                # The farthest point ends the left piece; boundary refinement may move it.
                stack_s[top] = k_best + 1
                stack_e[top] = e
                stack_s[top + 1] = s
                stack_e[top + 1] = k_best + 1
                top += 2
    return n_pieces


@njit(cache=True)
def _merge_pass(
    x: FloatArray,
    y: FloatArray,
    starts: IntArray,
    stops: IntArray,
    link: NDArray[np.bool_],
    same: NDArray[np.bool_],
    n_pieces: int,
    merge_distance_m: float,
) -> tuple[int, bool]:
    """One merge pass over the pieces in order, compacting them in place in ``O(pieces)``.

    A piece absorbs its successor while ``link`` allows it and every point of the union lies
    within ``merge_distance_m`` of the union's total-least-squares line; it then tries its
    new successor. Returns the new number of pieces and whether anything merged.
    """
    if n_pieces == 0:
        return 0, False
    w = 0
    merged = False
    for r in range(1, n_pieces):
        if (
            link[w]
            and stops[r] - starts[w] >= MIN_LINE_POINTS
            and _tls(x, y, starts[w], stops[r])[3] < merge_distance_m
        ):
            stops[w] = stops[r]
            merged = True
        else:
            w += 1
            starts[w] = starts[r]
            stops[w] = stops[r]
        link[w] = link[r]
        same[w] = same[r]
    return w + 1, merged


@njit(cache=True)
def split_and_merge(
    x: FloatArray,
    y: FloatArray,
    bounds: IntArray,
    joinable: NDArray[np.bool_],
    split_distance_m: float,
    merge_distance_m: float,
    min_points: int,
) -> IntArray:
    """Split-and-merge line segmentation inside clusters (Nguyen et al. 2005, "A comparison
    of line extraction algorithms using 2D laser rangefinder for indoor mobile robotics",
    Alg. 1; paper §III-C1).

    Split: a piece is divided at its point farthest from the chord of its first and last
    points while that distance exceeds ``split_distance_m`` (recursive end-point fit, run
    with an explicit stack). Merge: adjacent pieces of one cluster (or of two clusters
    separated only by a dropout, ``joinable``) are joined while every point of the union lies
    within ``merge_distance_m`` of the union's total-least-squares line, in at most
    ``MAX_MERGE_PASSES`` passes (fewer when a pass merges nothing). Before each merge
    pass and at the end, boundaries between adjacent pieces of a cluster are moved by up to
    ``BOUNDARY_SHIFT_POINTS`` points to the position that minimises the two lines' summed
    squared residuals (so the point at a corner goes to the wall it lies on and cannot block
    a merge).

    Args:
        x, y: ``(P,)`` float64 point coordinates, metres.
        bounds: ``(C + 1,)`` int64 cluster boundaries from :func:`breakpoints`.
        joinable: ``(max(C - 1, 0),)`` bool; ``joinable[c]`` lets the merge step join the
            last piece of cluster ``c`` with the first of cluster ``c + 1``.
        split_distance_m, merge_distance_m: Thresholds, metres.
        min_points: Pieces with fewer points are dropped at the end.

    Returns:
        ``(M, 2)`` int64 ``[start, stop)`` point ranges of the segments, in point order.
    """
    cap = x.shape[0] + 1
    starts = np.empty(cap, dtype=np.int64)
    stops = np.empty(cap, dtype=np.int64)
    owner = np.empty(cap, dtype=np.int64)
    n_pieces = _split_clusters(x, y, bounds, split_distance_m, starts, stops, owner)
    # link[i]: pieces i and i + 1 may merge (same cluster, or clusters split by a dropout);
    # same[i]: they are in one cluster (their boundary may move).
    link = np.zeros(cap, dtype=np.bool_)
    same = np.zeros(cap, dtype=np.bool_)
    for i in range(n_pieces - 1):
        same[i] = owner[i] == owner[i + 1]
        link[i] = same[i] or (
            owner[i + 1] == owner[i] + 1 and joinable[owner[i]] and stops[i] == starts[i + 1]
        )
    # Alternate boundary refinement and a merge pass, at most MAX_MERGE_PASSES times; stop
    # early after a pass that merges nothing (so a merge possible only after the last pass's
    # boundary refinement may be left undone).
    for _ in range(MAX_MERGE_PASSES):
        _refine_boundaries(x, y, starts, stops, same, n_pieces)
        n_pieces, merged = _merge_pass(x, y, starts, stops, link, same, n_pieces, merge_distance_m)
        if not merged:
            break
    _refine_boundaries(x, y, starts, stops, same, n_pieces)
    keep = (stops[:n_pieces] - starts[:n_pieces]) >= min_points
    out = np.empty((int(keep.sum()), 2), dtype=np.int64)
    out[:, 0] = starts[:n_pieces][keep]
    out[:, 1] = stops[:n_pieces][keep]
    return out
