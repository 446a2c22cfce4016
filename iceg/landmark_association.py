"""Distance-gated association of a scan's features with the feature map's landmarks, in the
new node's frame (docs/design.md "Feature map and time-validity"): the geometric pairs that
complete the matcher's inlier pairs, and the duplicate landmarks to merge; and the rows of
landmark or node ids in a sorted id table (:func:`lookup_sorted`) and the union of id sets
(:func:`sorted_union`); and a matching reference's landmarks and segments gathered into its
frame (:func:`reference_geometry`).

Compiled loops over (features x landmarks) instead of numpy's ``(K, n, 2)`` distance
temporaries; each distance is ``sqrt(dx^2 + dy^2)`` as ``np.linalg.norm`` computes it, so
the pairs are those of the numpy formulation (``tests/iceg/test_feature_map.py``). A scan's
whole association, from placing the landmarks in the new node's frame to the duplicates, is
one call (:func:`associate_scan`).
"""

from __future__ import annotations

import math

import numpy as np

from iceg.landmark_frames import _compose_rows, move_features, move_lines, move_points
from iceg_common.numba_loading import njit


@njit(cache=True, nogil=True)
def nearest_free_pairs(
    feature_xy: np.ndarray,
    feature_paired: np.ndarray,
    landmark_xy: np.ndarray,
    landmark_paired: np.ndarray,
    gate_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Pair each unpaired feature with its nearest unpaired landmark (the first on a tie)
    when it lies within ``gate_m``; a landmark wanted by several features goes to the one
    of lowest index.

    Args:
        feature_xy: ``(K, 2)`` float64 feature positions, metres.
        feature_paired: ``(K,)`` bool features already paired.
        landmark_xy: ``(n, 2)`` float64 landmark positions, same frame.
        landmark_paired: ``(n,)`` bool landmarks already paired.
        gate_m: Association gate, metres.

    Returns:
        ``(features, landmarks)`` ``(m,)`` int64 indices of the new pairs, by ascending
        landmark index.
    """
    owner = np.full(landmark_xy.shape[0], -1, dtype=np.int64)
    for i in range(feature_xy.shape[0]):
        if feature_paired[i]:
            continue
        best, bj = np.inf, -1
        for j in range(landmark_xy.shape[0]):
            if landmark_paired[j]:
                continue
            dx = feature_xy[i, 0] - landmark_xy[j, 0]
            dy = feature_xy[i, 1] - landmark_xy[j, 1]
            d = math.sqrt(dx * dx + dy * dy)
            if d < best:
                best, bj = d, j
        if bj >= 0 and best <= gate_m and owner[bj] < 0:
            owner[bj] = i
    landmarks = np.flatnonzero(owner >= 0)
    return owner[landmarks], landmarks


@njit(cache=True, nogil=True)
def within_gate_of_any(
    feature_xy: np.ndarray, features: np.ndarray, landmark_xy: np.ndarray, gate_m: float
) -> np.ndarray:
    """Which landmarks lie within ``gate_m`` of at least one of the ``features``.

    Args:
        feature_xy: ``(K, 2)`` float64 feature positions, metres.
        features: ``(q,)`` int64 indices into ``feature_xy``.
        landmark_xy: ``(n, 2)`` float64 landmark positions, same frame.
        gate_m: Gate, metres.

    Returns:
        ``(n,)`` bool.
    """
    out = np.zeros(landmark_xy.shape[0], dtype=np.bool_)
    for j in range(landmark_xy.shape[0]):
        for i in features:
            dx = feature_xy[i, 0] - landmark_xy[j, 0]
            dy = feature_xy[i, 1] - landmark_xy[j, 1]
            if math.sqrt(dx * dx + dy * dy) <= gate_m:
                out[j] = True
                break
    return out


@njit(cache=True, nogil=True)
def is_ascending(ids: np.ndarray) -> bool:
    """Whether the ``(n,)`` int64 ids never decrease (``(ids[1:] >= ids[:-1]).all()``)."""
    for k in range(1, ids.shape[0]):  # noqa: SIM110 (numba compiles no generator in all())
        if ids[k] < ids[k - 1]:
            return False
    return True


@njit(cache=True, nogil=True)
def lookup_sorted(table_ids: np.ndarray, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ids in a sorted id table: for each query id the first row whose id is not
    below it (``np.searchsorted``, side left), clipped to the last row, and whether that row
    holds the id; compiled, one call instead of numpy's four.

    Args:
        table_ids: ``(n,)`` int64 ids, ascending.
        query: ``(q,)`` int64 ids.

    Returns:
        ``pos`` ``(q,)`` int64 rows (0 for an empty table) and ``found`` ``(q,)`` bool.
    """
    n = table_ids.shape[0]
    if n == 0:
        return np.zeros(query.shape[0], dtype=np.int64), np.zeros(query.shape[0], dtype=np.bool_)
    pos = np.minimum(np.searchsorted(table_ids, query), n - 1)
    return pos, table_ids[pos] == query


@njit(cache=True, nogil=True)
def _row_of(table: np.ndarray, value: int) -> int:
    """The row of ``value`` in the ascending ``table`` (``(n,)`` int64), -1 when absent:
    :func:`lookup_sorted` of one id."""
    n = table.shape[0]
    if n == 0:
        return -1
    k = min(np.searchsorted(table, value), n - 1)
    return k if table[k] == value else -1


@njit(cache=True, nogil=True)
def rows_of_nodes(want: np.ndarray, anchor: np.ndarray, last_node: np.ndarray) -> np.ndarray:
    """Ascending rows whose ``anchor`` or ``last_node`` is one of the nodes ``want``
    (``(w,)`` int64, ascending and unique): a range test when ``want`` is a run of
    consecutive ids (a local map's recent nodes), a binary search otherwise; the rows of
    ``lookup_sorted(want, anchor)[1] | lookup_sorted(want, last_node)[1]``.

    Args:
        anchor, last_node: ``(L,)`` int64 node ids of each row.

    Returns:
        ``(k,)`` int64 rows.
    """
    n_w = want.shape[0]
    out = np.empty(anchor.shape[0], dtype=np.int64)
    if n_w == 0:
        return out[:0].copy()
    lo, hi = want[0], want[n_w - 1]
    run = hi - lo == n_w - 1
    k = 0
    for r in range(anchor.shape[0]):
        a, b = anchor[r], last_node[r]
        if run:
            hit = (lo <= a and a <= hi) or (lo <= b and b <= hi)
        else:
            hit = _row_of(want, a) >= 0 or _row_of(want, b) >= 0
        if hit:
            out[k] = r
            k += 1
    return out[:k].copy()


@njit(cache=True, nogil=True)
def rows_taking_part(
    last_node: np.ndarray, first_node: int, ids: np.ndarray, reference_ids: np.ndarray
) -> np.ndarray:
    """Ascending rows whose ``last_node`` is ``first_node`` or later, or whose id is one of
    ``reference_ids``: ``np.flatnonzero`` of ``last_node >= first_node`` with the rows of
    ``lookup_sorted(ids, reference_ids)`` that hold their id set, in one pass.

    Args:
        last_node, ids: ``(L,)`` int64 each row's last matching node and its id (ascending).
        reference_ids: ``(q,)`` int64 ids, any order (absent ones take no row).

    Returns:
        ``(k,)`` int64 rows. Raises nothing.
    """
    part = last_node >= first_node
    for q in range(reference_ids.shape[0]):
        r = _row_of(ids, reference_ids[q])
        if r >= 0:
            part[r] = True
    return np.flatnonzero(part)


@njit(cache=True, nogil=True)
def sorted_union(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.union1d(a, b)``: the ids in either array, ascending, each once; one compiled
    pass instead of numpy's concatenation, sort and unique.

    Args:
        a, b: ``(n,)`` and ``(m,)`` int64 ids, any order, repeats allowed.

    Returns:
        ``(k,)`` int64 sorted unique ids.
    """
    both = np.empty(a.shape[0] + b.shape[0], dtype=np.int64)
    both[: a.shape[0]] = a
    both[a.shape[0] :] = b
    both.sort()
    k = 0
    for i in range(both.shape[0]):
        if k == 0 or both[i] != both[k - 1]:
            both[k] = both[i]
            k += 1
    return both[:k].copy()


@njit(cache=True, nogil=True)
def associate_scan(
    part: np.ndarray,
    lm_id: np.ndarray,
    lm_anchor: np.ndarray,
    lm_xy: np.ndarray,
    tab_ids: np.ndarray,
    tab_poses: np.ndarray,
    new_inverse: np.ndarray,
    inlier_pairs: np.ndarray,
    ref_ids: np.ndarray,
    feature_xy: np.ndarray,
    gate_m: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One scan's association with the landmarks taking part in its bookkeeping
    (``FeatureMap._bookkeep``), in one pass: the numpy formulation's answers and bits.

    The landmarks of ``part`` whose anchor has a pose are placed in the new node's frame
    (``se2.between`` of the anchors, :func:`~iceg.landmark_frames.poses_in_frame`'s
    expressions, and their positions as ``move_points`` moves them). The matcher's inlier
    pairs whose landmark takes part come first; then each unpaired feature takes its
    nearest unpaired landmark within ``gate_m`` (:func:`nearest_free_pairs`); the other
    landmarks within ``gate_m`` of a paired feature are duplicates to merge
    (:func:`within_gate_of_any`).

    Args:
        part: ``(p,)`` int64 ascending rows of the landmarks taking part.
        lm_id, lm_anchor: ``(L,)`` int64 every landmark's id (ascending) and anchor node.
        lm_xy: ``(L, 2)`` float64 every landmark's position, its anchor's frame, metres.
        tab_ids: ``(N,)`` int64 ascending nodes with a pose; ``tab_poses`` ``(N, 3)`` float64
            their poses, map frame.
        new_inverse: ``(5,)`` float64 the new node's inverse pose ``x, y, theta`` and that
            theta's cosine and sine.
        inlier_pairs: ``(Q, 2)`` int64 the match's pairs ``[new feature, reference row]``.
        ref_ids: ``(R,)`` int64 landmark id of each reference row.
        feature_xy: ``(K, 2)`` float64 the new features' positions, new node's frame.
        gate_m: Association gate, metres.

    Returns:
        ``rows`` ``(n,)`` int64 the landmarks placed; ``anchor_in_new`` ``(n, 3)`` float64
        their anchors' poses and ``xy_new`` ``(n, 2)`` their positions, new node's frame;
        ``slot`` ``(L,)`` int64 each row's index into ``rows`` (-1: not placed); the pairs
        ``pair_new``, ``pair_row`` ``(m,)`` int64 (feature, landmark row); and
        ``merge_rows`` ``(d,)`` int64 the duplicates' rows.
    """
    n_lm = lm_id.shape[0]
    placed = np.empty(part.shape[0], dtype=np.int64)
    pos = np.empty(part.shape[0], dtype=np.int64)
    n = 0
    for t in range(part.shape[0]):
        k = _row_of(tab_ids, lm_anchor[part[t]])
        if k >= 0:
            placed[n] = part[t]
            pos[n] = k
            n += 1
    rows = placed[:n].copy()
    anchor_in_new = _compose_rows(
        new_inverse[0],
        new_inverse[1],
        new_inverse[2],
        new_inverse[3],
        new_inverse[4],
        tab_poses,
        pos[:n],
    )
    xy_new = np.empty((n, 2))
    slot = np.full(n_lm, -1, dtype=np.int64)
    for i in range(n):
        c, s = math.cos(anchor_in_new[i, 2]), math.sin(anchor_in_new[i, 2])
        px, py = lm_xy[rows[i], 0], lm_xy[rows[i], 1]
        xy_new[i, 0] = c * px - s * py + anchor_in_new[i, 0]
        xy_new[i, 1] = s * px + c * py + anchor_in_new[i, 1]
        slot[rows[i]] = i
    # the matcher's pairs whose landmark takes part
    k_new = feature_xy.shape[0]
    n_ref = ref_ids.shape[0]
    first_new = np.empty(inlier_pairs.shape[0], dtype=np.int64)
    first_row = np.empty(inlier_pairs.shape[0], dtype=np.int64)
    m = 0
    for t in range(inlier_pairs.shape[0]):
        a, b = inlier_pairs[t, 0], inlier_pairs[t, 1]
        if a < 0 or a >= k_new or b < 0 or b >= n_ref:
            continue
        k = _row_of(lm_id, ref_ids[b])
        if k >= 0 and slot[k] >= 0:
            first_new[m] = a
            first_row[m] = k
            m += 1
    feature_paired = np.zeros(k_new, dtype=np.bool_)
    slot_paired = np.zeros(n, dtype=np.bool_)
    for t in range(m):
        feature_paired[first_new[t]] = True
        slot_paired[slot[first_row[t]]] = True
    geo_new, geo_slot = nearest_free_pairs(feature_xy, feature_paired, xy_new, slot_paired, gate_m)
    pair_new = np.concatenate((first_new[:m], geo_new))
    pair_row = np.concatenate((first_row[:m], rows[geo_slot]))
    if pair_new.shape[0] == 0 or n == 0:
        return rows, anchor_in_new, xy_new, slot, pair_new, pair_row, np.zeros(0, np.int64)
    close = within_gate_of_any(feature_xy, pair_new, xy_new, gate_m)
    for t in range(pair_row.shape[0]):
        close[slot[pair_row[t]]] = False
    return rows, anchor_in_new, xy_new, slot, pair_new, pair_row, rows[np.flatnonzero(close)]


@njit(cache=True, nogil=True)
def reference_geometry(
    tab_ids: np.ndarray,
    tab_poses: np.ndarray,
    frame_inverse: np.ndarray,
    lm_rows: np.ndarray,
    lm_anchor: np.ndarray,
    lm_xy: np.ndarray,
    lm_cov: np.ndarray,
    lm_dirs: np.ndarray,
    seg_rows: np.ndarray,
    seg_node: np.ndarray,
    seg_ep: np.ndarray,
    seg_lines: np.ndarray,
    seg_cov: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A matching reference's geometry in its frame (``FeatureMap.reference``), in one
    pass: the landmarks of ``lm_rows`` whose anchor has a pose and the segments of
    ``seg_rows``, each placed by its node's pose in the frame (the anchors as
    :func:`~iceg.landmark_frames.poses_in_frame` places them, the landmarks as
    :func:`~iceg.landmark_frames.move_features` moves them, the segments' lines as
    :func:`~iceg.landmark_frames.move_lines` and their endpoints as
    :func:`~iceg.landmark_frames.move_points`): the same calls, so the same bits.

    Args:
        tab_ids: ``(N,)`` int64 ascending nodes with a pose; ``tab_poses`` ``(N, 3)``
            float64 their poses, map frame.
        frame_inverse: ``(5,)`` float64 the frame's inverse pose and its heading's cosine and
            sine (:func:`~iceg.landmark_frames.frame_inverse`).
        lm_rows: ``(k,)`` int64 ascending landmark rows to place.
        lm_anchor: ``(L,)`` int64 every landmark's anchor node; ``lm_xy`` ``(L, 2)``,
            ``lm_cov`` ``(L, 2, 2)``, ``lm_dirs`` ``(L, 2, 2)`` float64 its position (metres),
            position covariance (m²) and wall directions, anchor's frame.
        seg_rows: ``(m,)`` int64 segment rows to place, each of a node in ``tab_ids``.
        seg_node: ``(M,)`` int64 every segment's node; ``seg_ep`` ``(M, 2, 2)``,
            ``seg_lines`` ``(M, 2)``, ``seg_cov`` ``(M, 2, 2)`` float64 its endpoints
            (metres), Hessian line ``(alpha_rad, rho_m)`` and the line's covariance, node's
            frame.

    Returns:
        ``rows`` ``(n,)`` int64 the landmarks placed; their positions ``(n, 2)``,
        covariances ``(n, 2, 2)`` and directions ``(n, 2, 2)``; the segments' endpoints
        ``(m, 2, 2)``, lines ``(m, 2)`` and line covariances ``(m, 2, 2)``; all float64 in
        the frame.
    """
    fi = frame_inverse
    pos, found = lookup_sorted(tab_ids, lm_anchor[lm_rows])
    keep = np.flatnonzero(found)
    rows = lm_rows[keep]
    anchors = _compose_rows(fi[0], fi[1], fi[2], fi[3], fi[4], tab_poses, pos[keep])
    xy, cov, dirs = move_features(rows, anchors, lm_xy, lm_cov, lm_dirs)
    seg_pos, _ = lookup_sorted(tab_ids, seg_node[seg_rows])
    nodes = _compose_rows(fi[0], fi[1], fi[2], fi[3], fi[4], tab_poses, seg_pos)
    lines, line_cov = move_lines(seg_rows, nodes, seg_lines, seg_cov)
    return rows, xy, cov, dirs, move_points(nodes, seg_ep[seg_rows], True), lines, line_cov
