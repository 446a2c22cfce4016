"""Steps 2-3 of feature extraction: breakpoints, split-and-merge, maximum-likelihood lines.

docs/design.md "ICE matching, step by step", steps 2-3; paper §III-C1.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from iceg.features.config import FeatureConfig
from iceg.features.geometry import norm
from iceg.features.lines import fit_lines
from iceg.features.points import BeamPoints
from iceg.features.segmentation import breakpoints, split_and_merge

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


class Segments(NamedTuple):
    """M line segments of one scan, robot frame."""

    point_range: IntArray  # (M, 2) int64 [start, stop) indices into BeamPoints.points
    lines: FloatArray  # (M, 2) float64 (alpha_rad, rho_m), rho >= 0
    cov: FloatArray  # (M, 2, 2) float64 covariance of (alpha, rho): rad², rad·m, m²
    endpoints: FloatArray  # (M, 2, 2) float64 first / last point projected on the line, m
    end_beam: IntArray  # (M, 2) int64 scan beam index of the first / last point
    spacing: FloatArray  # (M, 2) float64 along-wall beam spacing at each endpoint, m
    normals: FloatArray  # (M, 2) float64 unit line normals (cos alpha, sin alpha)


def segment_point_ranges(beams: BeamPoints, cfg: FeatureConfig) -> IntArray:
    """Point ranges of the segments: adaptive breakpoints (Borges & Aldon 2004, eq. 8), then
    split-and-merge inside clusters (paper §III-C1; Nguyen et al. 2005, Alg. 1), merging
    across at most ``cfg.dropout_max_beams`` invalid beams.

    Args:
        beams: The scan's points (:func:`iceg.features.points.beam_points`).
        cfg: ``sigma_range_m``, ``breakpoint_lambda_deg``, ``dropout_max_beams``,
            ``split_distance_m``, ``merge_distance_m``, ``min_segment_points`` are read.

    Returns:
        ``(M, 2)`` int64 ``[start, stop)`` indices into ``beams.points``, in point order.
    """
    points, beam_index = beams.points, beams.beam_index
    bounds = breakpoints(
        points,
        beams.point_ranges,
        beams.angles[beams.valid],
        beam_index,
        cfg.sigma_range_m,
        math.radians(cfg.breakpoint_lambda_deg),
    )
    inner = bounds[1:-1]
    gap_beams = beam_index[inner] - beam_index[inner - 1] - 1
    joinable = (gap_beams >= 1) & (gap_beams <= cfg.dropout_max_beams)
    return split_and_merge(
        np.ascontiguousarray(points[:, 0]),
        np.ascontiguousarray(points[:, 1]),
        bounds,
        joinable,
        cfg.split_distance_m,
        cfg.merge_distance_m,
        cfg.min_segment_points,
    )


def endpoint_spacing(
    beams: BeamPoints, end_beam: IntArray, normals: FloatArray, cfg: FeatureConfig
) -> FloatArray:
    """Along-wall distance between consecutive beams at each segment endpoint.

    ``r dphi / max(|cos incidence|, cos(eow_max_incidence_deg))`` with ``r`` the endpoint
    beam's range, ``dphi`` the mean beam step and the incidence measured from the wall
    normal: at grazing incidence consecutive beams land far apart, so gaps near an endpoint
    scale with it.

    Args:
        beams: The scan's beams.
        end_beam: ``(M, 2)`` int64 beam index of each segment's first and last point.
        normals: ``(M, 2)`` float64 unit normals of the segments' lines.
        cfg: ``eow_max_incidence_deg`` is read.

    Returns:
        ``(M, 2)`` float64 metres.
    """
    angles = beams.angles
    n_beams = angles.shape[0]
    dphi = (angles[-1] - angles[0]) / max(n_beams - 1, 1)
    cos_max_inc = math.cos(math.radians(cfg.eow_max_incidence_deg))
    cos_inc_end = np.abs(np.einsum("mj,mej->me", normals, beams.dirs[end_beam]))
    spacing: FloatArray = beams.ranges[end_beam] * dphi / np.maximum(cos_inc_end, cos_max_inc)
    return spacing


def line_segments(beams: BeamPoints, cfg: FeatureConfig) -> Segments:
    """Line segments of a scan with their maximum-likelihood lines (docs/design.md steps 2-3).

    Segments from :func:`segment_point_ranges`, lines by weighted total least squares
    (:func:`iceg.features.lines.fit_lines`, Pfister et al. 2003); segments shorter than
    ``cfg.min_segment_length_m`` between their projected endpoints (Nguyen et al. 2005,
    L_min) are dropped.

    Args:
        beams: The scan's points; at least one.
        cfg: Segmentation thresholds, ``sigma_bearing_deg`` and ``min_segment_length_m``.

    Returns:
        :class:`Segments` (M may be 0).
    """
    seg_range = segment_point_ranges(beams, cfg)
    lines, seg_cov, endpoints = fit_lines(
        beams.points,
        beams.point_ranges,
        beams.dirs[beams.valid],
        seg_range,
        cfg.sigma_range_m,
        math.radians(cfg.sigma_bearing_deg),
        cfg.line_variance_from_residuals,
    )
    keep = norm(endpoints[:, 1] - endpoints[:, 0]) >= cfg.min_segment_length_m
    seg_range, lines = seg_range[keep], lines[keep]
    normals = np.stack([np.cos(lines[:, 0]), np.sin(lines[:, 0])], axis=1)
    bi = beams.beam_index
    end_beam = np.stack([bi[seg_range[:, 0]], bi[seg_range[:, 1] - 1]], axis=1)
    return Segments(
        point_range=seg_range,
        lines=lines,
        cov=seg_cov[keep],
        endpoints=endpoints[keep],
        end_beam=end_beam,
        spacing=endpoint_spacing(beams, end_beam, normals, cfg),
        normals=normals,
    )
