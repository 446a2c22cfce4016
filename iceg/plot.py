"""Plot helpers: each takes a matplotlib ``ax``, draws on it, and returns the artists it drew.

Nothing here creates a figure, changes global matplotlib state or shows a window.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    from matplotlib.artist import Artist
    from matplotlib.axes import Axes
    from matplotlib.container import BarContainer
    from matplotlib.lines import Line2D

    from iceg.grid import OccupancyGrid


def grid(ax: Axes, grid: OccupancyGrid, trajectory: ArrayLike | None = None) -> list[Artist]:
    """Draw an occupancy grid's probability map in metric world coordinates.

    Args:
        ax: The axes to draw on; its aspect is set equal and its axes labelled in metres.
        grid: The map; drawn as ``imshow(origin="lower", extent=grid.extent_xy)`` in grey
            (white free, black occupied, mid-grey unknown).
        trajectory: ``(N, 2+)`` world positions ``[x_m, y_m, ...]`` drawn as a red line,
            or ``None``.

    Returns:
        ``[image]`` or ``[image, trajectory_line]``.
    """
    image = ax.imshow(
        grid.probabilities(),
        cmap="gray_r",
        vmin=0.0,
        vmax=1.0,
        origin="lower",
        extent=grid.extent_xy,
        interpolation="nearest",
    )
    artists: list[Artist] = [image]
    if trajectory is not None:
        t = np.asarray(trajectory, dtype=np.float64)
        (line,) = ax.plot(t[:, 0], t[:, 1], color="tab:red", linewidth=1.0, label="trajectory")
        artists.append(line)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    return artists


if TYPE_CHECKING:
    from frontends.scan import LaserScan
    from iceg.types import ScanFeatures


def scan_features(
    ax: Axes, scan: LaserScan, features: ScanFeatures, arrow_length_m: float = 0.5
) -> list[Artist]:
    """Draw a scan's points, line segments and ICE features in its robot frame (paper Fig. 1-2).

    Points grey; segments as coloured lines; Corners as red squares with arrows along both
    edges; ends of wall (EOW) as blue circles with an arrow along the wall; Intersections as
    green crosses joined by dotted lines to the nearer endpoint of each of their segments.
    The laser origin is a black triangle.

    Args:
        ax: The axes to draw on; aspect set equal, axes labelled in metres.
        scan: The scan (its laser offset marks the sensor; its points are drawn if
            ``features.points_xy`` is empty).
        features: ``iceg.features.extract(scan)``, robot frame.
        arrow_length_m: Length of the direction arrows, metres.

    Returns:
        The artists drawn.
    """
    from iceg.types import FeatureKind

    artists: list[Artist] = []
    pts = features.points_xy if features.points_xy.shape[0] else scan.points_xy()
    if pts.shape[0]:
        (p,) = ax.plot(pts[:, 0], pts[:, 1], ".", color="0.55", markersize=2.5, label="points")
        artists.append(p)
    off = np.asarray(scan.laser_offset, dtype=np.float64)
    (o,) = ax.plot([off[0]], [off[1]], "^", color="k", markersize=7, label="laser")
    artists.append(o)
    for m, ends in enumerate(features.seg_endpoints):
        (s,) = ax.plot(ends[:, 0], ends[:, 1], "-", linewidth=2.0, color=f"C{m % 10}")
        artists.append(s)
    style = {
        FeatureKind.CORNER: ("s", "tab:red", "corner"),
        FeatureKind.EOW: ("o", "tab:blue", "end of wall"),
        FeatureKind.INTERSECTION: ("x", "tab:green", "intersection"),
    }
    for kind, (marker, color, label) in style.items():
        sel = np.flatnonzero(features.kind == kind)
        if sel.size:
            artists += _feature_markers(ax, features, sel, marker, color, label, arrow_length_m)
        if sel.size and kind == FeatureKind.INTERSECTION:
            artists += _intersection_links(ax, features, sel, color)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m] (robot frame)")
    ax.set_ylabel("y [m] (robot frame)")
    return artists


def _feature_markers(
    ax: Axes,
    features: ScanFeatures,
    sel: NDArray[np.int64],
    marker: str,
    color: str,
    label: str,
    arrow_length_m: float,
) -> list[Artist]:
    """Markers of the features ``sel`` and arrows along their (finite) directions."""
    xy = features.xy[sel]
    (mk,) = ax.plot(
        xy[:, 0],
        xy[:, 1],
        marker,
        color=color,
        markerfacecolor="none",
        markersize=9,
        markeredgewidth=1.8,
        label=label,
    )
    artists: list[Artist] = [mk]
    d = features.directions[sel].reshape(-1, 2)
    base = np.repeat(xy, 2, axis=0)
    ok = np.all(np.isfinite(d), axis=1)
    if np.any(ok):
        q = ax.quiver(
            base[ok, 0],
            base[ok, 1],
            d[ok, 0] * arrow_length_m,
            d[ok, 1] * arrow_length_m,
            angles="xy",
            scale_units="xy",
            scale=1.0,
            color=color,
            width=0.004,
        )
        artists.append(q)
    return artists


def _intersection_links(
    ax: Axes, features: ScanFeatures, sel: NDArray[np.int64], color: str
) -> list[Artist]:
    """Dotted lines from each Intersection in ``sel`` to the nearer endpoint of its segments."""
    artists: list[Artist] = []
    for k in sel:
        for m in features.segment_ids[k]:
            if m < 0:
                continue
            ends = features.seg_endpoints[m]
            near = ends[np.argmin(np.linalg.norm(ends - features.xy[k], axis=1))]
            (ln,) = ax.plot(
                [near[0], features.xy[k, 0]],
                [near[1], features.xy[k, 1]],
                ":",
                color=color,
                linewidth=1.0,
            )
            artists.append(ln)
    return artists


def covariance_ellipses(
    ax: Axes,
    poses: ArrayLike,
    covariances: ArrayLike,
    n_sigma: float = 3.0,
    color: str = "tab:blue",
) -> list[Artist]:
    """Draw the ``n_sigma`` position ellipse of each pose's covariance.

    Args:
        ax: Matplotlib axes (map frame, metres).
        poses: ``(K, 3)`` poses ``[x_m, y_m, theta_rad]``, map frame.
        covariances: ``(K, 3, 3)`` pose covariances in the tangent space of each pose (body
            frame, gtsam convention, e.g. ``PoseGraph.marginal_covariance``); the position
            block is rotated into the map frame by the pose's heading.
        n_sigma: ellipse scale in standard deviations.
        color: edge colour.

    Returns:
        The ellipse patches.
    """
    from matplotlib.patches import Ellipse

    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    c = np.asarray(covariances, dtype=np.float64).reshape(-1, 3, 3)
    artists: list[Artist] = []
    for (x, y, th), cov in zip(p, c, strict=True):
        rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        cov_xy = rot @ cov[:2, :2] @ rot.T
        vals, vecs = np.linalg.eigh(cov_xy)
        width, height = 2.0 * n_sigma * np.sqrt(np.clip(vals[::-1], 0.0, None))
        angle = np.degrees(np.arctan2(vecs[1, 1], vecs[0, 1]))
        patch = Ellipse((x, y), width, height, angle=angle, fill=False, color=color, lw=1.2)
        ax.add_patch(patch)
        artists.append(patch)
    ax.set_aspect("equal")
    return artists


def relation_errors(ax: Axes, per_relation: ArrayLike, bins: int = 40) -> list[Artist]:
    """Histogram of the translational relation errors (Kümmerle et al. 2009).

    Args:
        ax: Matplotlib axes.
        per_relation: ``(M, 2)`` ``[trans_err_m, rot_err_deg]`` as returned by
            :func:`iceg.evaluation.relation_errors` (NaN rows are skipped).
        bins: histogram bins.

    Returns:
        The bar patches.
    """
    e = np.asarray(per_relation, dtype=np.float64).reshape(-1, 2)
    e = e[np.all(np.isfinite(e), axis=1)]
    _, _, bars = ax.hist(e[:, 0], bins=bins, color="tab:blue")
    ax.set_xlabel("translational relation error [m]")
    ax.set_ylabel("relations")
    return list(cast("BarContainer", bars))


def nees_cdf(ax: Axes, nees: ArrayLike, label: str, reference: bool = True) -> list[Line2D]:
    """Empirical distribution of 3-dof NEES values against the chi-square distribution an
    honest covariance gives them (:mod:`iceg.consistency`), on a logarithmic NEES axis: a
    curve right of the reference is overconfident, left of it conservative.

    Args:
        ax: Matplotlib axes.
        nees: ``(k,)`` float64 NEES values (non-finite values are left out), e.g.
            ``FactorNees.nees[FactorNees.kind == "scan_match"]``.
        label: Legend label of the curve.
        reference: Also draw the chi-square (3 dof) CDF, dashed.

    Returns:
        The step line, and the reference line when drawn.
    """
    from scipy.special import chdtr  # the chi-square CDF; lazy: scipy is slow to import

    v = np.sort(np.asarray(nees, dtype=np.float64).ravel())
    v = v[np.isfinite(v) & (v > 0)]
    fraction = np.arange(1, v.size + 1) / max(v.size, 1)
    (line,) = ax.step(v, fraction, where="post", label=f"{label} ({v.size})")
    artists = [line]
    if reference:
        lo = min(float(v[0]) if v.size else 1e-2, 1e-2)
        hi = max(float(v[-1]) if v.size else 1e2, 1e2)
        x = np.geomspace(lo, hi, 200)
        (ref,) = ax.plot(x, chdtr(3, x), "k--", linewidth=1.0, label="chi-square, 3 dof")
        artists.append(ref)
    ax.set_xscale("log")
    ax.set_xlabel("NEES")
    ax.set_ylabel("fraction at most")
    return artists
