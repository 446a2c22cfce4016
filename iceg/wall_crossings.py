"""Robot steps that pass through walls: a physical test of a map's consistency.

A robot cannot drive through a wall that stood where it drove. In a map made of two
sessions, a step of one robot's path (two nodes joined by odometry) that crosses a wall the
other session saw from many nodes means the alignment of the sessions is wrong, or the
wall was not there (a door that was closed). The number of nodes that saw the wall tells
the two apart: a person or a door seen once or twice is transient, a wall seen from as many
nodes as the feature map needs before it judges a landmark (``feature_map.min_expected``,
paper §III-C3) is structure.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Steps tested against every wall at once (bounds the temporaries: steps x walls).
_CHUNK_STEPS = 256


def nodes_of_walls_crossed(
    steps: FloatArray, walls: FloatArray, wall_node: IntArray, end_margin_m: float
) -> IntArray:
    """For each robot step, how many distinct nodes saw a wall that it passes through.

    A step crosses a wall when the two segments intersect at a point more than
    ``end_margin_m`` from either end of the wall (a step past a door jamb, whose
    extracted end is uncertain, does not count).

    Args:
        steps: ``(S, 2, 2)`` float64 start and end positions of each step (metres, map
            frame).
        walls: ``(M, 2, 2)`` float64 wall endpoints (metres, map frame).
        wall_node: ``(M,)`` int64 the node that saw each wall.
        end_margin_m: Margin at each end of a wall (metres).

    Returns:
        ``(S,)`` int64 the number of distinct nodes of the walls each step crosses.
    """
    out = np.zeros(steps.shape[0], dtype=np.int64)
    if steps.shape[0] == 0 or walls.shape[0] == 0:
        return out
    w0, w1 = walls[:, 0], walls[:, 1]
    w_lo, w_hi = np.minimum(w0, w1), np.maximum(w0, w1)
    length = np.hypot(*(w1 - w0).T)
    for first in range(0, steps.shape[0], _CHUNK_STEPS):
        chunk = steps[first : first + _CHUNK_STEPS]
        p0, p1 = chunk[:, 0], chunk[:, 1]
        lo, hi = np.minimum(p0, p1), np.maximum(p0, p1)
        near = np.all((lo[:, None] <= w_hi[None]) & (hi[:, None] >= w_lo[None]), axis=2)
        si, wi = np.nonzero(near)
        r = p1[si] - p0[si]
        d = w1[wi] - w0[wi]
        q = w0[wi] - p0[si]
        den = r[:, 0] * d[:, 1] - r[:, 1] * d[:, 0]
        ok = np.abs(den) > 1e-12
        den = np.where(ok, den, 1.0)
        t = (q[:, 0] * d[:, 1] - q[:, 1] * d[:, 0]) / den  # along the step
        u = (q[:, 0] * r[:, 1] - q[:, 1] * r[:, 0]) / den  # along the wall
        along = u * length[wi]
        hit = ok & (t >= 0.0) & (t <= 1.0)
        hit &= (along >= end_margin_m) & (along <= length[wi] - end_margin_m)
        pairs = np.unique(np.column_stack([si[hit], wall_node[wi[hit]]]), axis=0)
        steps_hit, counts = np.unique(pairs[:, 0], return_counts=True)
        out[first + steps_hit] = counts
    return out
