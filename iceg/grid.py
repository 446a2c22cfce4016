"""Occupancy grid mapping: log-odds and binary maps rendered from scans along a trajectory.

The core is pure: :func:`render` and :func:`render_ranges` take scans (or range arrays) and
one pose per scan and return an :class:`OccupancyGrid`; nothing here reads a file. The
``write_*`` functions export a grid atomically (temporary file beside the target, then
``os.replace``) to the ROS map_server pair (PGM + YAML), to a PNG with the trajectory drawn
over it, and to a compressed numpy archive.

Grid convention (the ROS ``nav_msgs/OccupancyGrid`` convention): ``log_odds[row, col]`` with
row 0 the **lowest** y and column 0 the lowest x; cell ``(row, col)`` covers the world
square ``[ox + col*res, ox + (col+1)*res) x [oy + row*res, oy + (row+1)*res)`` where
``origin_xy = (ox, oy)`` is the world coordinate of the lower-left corner of cell ``(0, 0)``.
Image exports flip the rows (highest y first), as map_server expects.

Sources: log-odds occupancy mapping with an inverse sensor model, Thrun, Burgard & Fox,
*Probabilistic Robotics*, MIT Press 2005, ch. 9 (Table 9.1 occupancy_grid_mapping, Table 9.2
inverse_range_sensor_model); default log-odds and clamping from OctoMap, Hornung et al.,
Autonomous Robots 34:189-206, 2013; ray traversal from Amanatides & Woo, "A Fast Voxel
Traversal Algorithm for Ray Tracing", Eurographics 1987; the binary map of the ICE paper
(§IV, Fig. 3-4: "the Grid based mapping was based on binary distribution").
"""

from __future__ import annotations

import functools
import itertools
import logging
import math
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal, NamedTuple

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

from frontends.scan import LaserScan
from iceg.features.prefetch import CoreWatch
from iceg_common.atomic import atomic_path, atomic_write
from iceg_common.errors import GridError
from iceg_common.numba_loading import njit
from iceg_common.se2 import compose

if TYPE_CHECKING:
    from PIL import Image

__all__ = [
    "BeamChunk",
    "GridConfig",
    "GridError",
    "OccupancyGrid",
    "TiledGrid",
    "render",
    "render_ranges",
    "render_tiled",
    "render_tiled_beams",
    "render_tiled_chunks",
    "write_map_server",
    "write_npz",
    "write_png",
]

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: Scans per chunk of :func:`render_tiled_chunks` (about 360 beams each: ~40 MB of work
#: arrays per chunk).
CHUNK_SCANS = 1000

#: map_server PGM grey levels (ROS map_server ``map_saver`` convention).
PGM_OCCUPIED = 0
PGM_FREE = 254
PGM_UNKNOWN = 205


#: Sentinel default of OccupancyGrid.hits / misses: replaced by zeros of the grid's shape.
_NO_COUNTS: NDArray[np.int32] = np.zeros((0, 0), dtype=np.int32)


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


class GridConfig(BaseModel):
    """Occupancy-grid parameters (units in the field names)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    resolution_m: float = Field(
        default=0.05,
        gt=0.0,
        description="Cell edge length in metres (paper §IV renders a metric grid).",
    )
    l_occ: float = Field(
        default=0.85,
        gt=0.0,
        description="Log-odds added to the cell a beam ends in (inverse sensor model, Thrun et "
        "al. 2005, Probabilistic Robotics ch. 9, Table 9.2 l_occ); 0.85 = p_hit 0.7 as in "
        "OctoMap (Hornung et al. 2013).",
    )
    l_free: float = Field(
        default=-0.4,
        lt=0.0,
        description="Log-odds added to every cell a beam passes through before its endpoint "
        "(Thrun et al. 2005, ch. 9, Table 9.2 l_free); -0.4 = p_miss 0.4 as in OctoMap.",
    )
    l_min: float = Field(
        default=-2.0,
        lt=0.0,
        description="Lower clamping limit of a cell's log-odds (p 0.12), so a cell can turn "
        "occupied again after a change (OctoMap clamping, Hornung et al. 2013 §III-C).",
    )
    l_max: float = Field(
        default=3.5,
        gt=0.0,
        description="Upper clamping limit of a cell's log-odds (p 0.97; OctoMap clamping).",
    )
    occupied_thresh: float = Field(
        default=0.65,
        gt=0.0,
        lt=1.0,
        description="A cell with probability above this is occupied (ROS map_server default).",
    )
    free_thresh: float = Field(
        default=0.196,
        gt=0.0,
        lt=1.0,
        description="A cell with probability below this is free (ROS map_server default).",
    )
    margin_m: float = Field(
        default=1.0, ge=0.0, description="Border added around the poses and beam endpoints, metres."
    )
    range_max_m: float | None = Field(
        default=30.0,
        gt=0.0,
        description="Beams at or beyond this range (or the scan's own range_max_m, whichever "
        "is smaller) are treated as no-return: no hit is drawn. Long beams smear walls under "
        "small heading errors (1 mrad at 30 m is 3 cm). None: the scan's range_max_m only.",
    )
    no_return_clear_m: float | None = Field(
        default=None,
        gt=0.0,
        description="None: a no-return beam changes nothing. Otherwise the cells along a "
        "no-return beam are marked free up to this distance from the laser, metres.",
    )
    mode: Literal["logodds", "binary"] = Field(
        default="logodds",
        description="'logodds': Bayesian log-odds map (Thrun et al. ch. 9, paper Fig. 5). "
        "'binary': the paper's binary map (§IV, Fig. 3-4): a cell is occupied if beams ended "
        "in it in at least one scan and in at least as many scans as rays passed through it, "
        "free if rays passed through it in more scans than beams ended in it, else unknown.",
    )
    threads: int = Field(
        default=0,
        ge=0,
        description="Threads tracing the beams, each over its own band of rows (every cell "
        "is updated by one thread, in scan order, so the map is identical with any number). "
        "0: 2 when a core is idle (iceg.features.prefetch.auto_workers, the cores watched "
        "through the render's first passes: CoreWatch), else 1.",
    )
    max_cells: int = Field(
        default=25_000_000,
        gt=0,
        description="Refuse to store more cells than this (about 20 bytes per cell while "
        "rendering). Rendering stores only the 64x64-cell tiles the beams cross (render_tiled), "
        "so this bounds the area the rays touch; a dense grid (render, OccupancyGrid) also "
        "bounds its full extent by it.",
    )

    @model_validator(mode="after")
    def _check_thresholds(self) -> GridConfig:
        if not self.free_thresh < self.occupied_thresh:
            raise ValueError(
                f"free_thresh ({self.free_thresh}) must be below occupied_thresh "
                f"({self.occupied_thresh})"
            )
        if not self.l_min < _logit(self.free_thresh):
            raise ValueError(
                f"l_min ({self.l_min}) must be below logit(free_thresh) "
                f"({_logit(self.free_thresh):.3f}), or no cell can ever be free"
            )
        if not self.l_max > _logit(self.occupied_thresh):
            raise ValueError(
                f"l_max ({self.l_max}) must be above logit(occupied_thresh) "
                f"({_logit(self.occupied_thresh):.3f}), or no cell can ever be occupied"
            )
        return self


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """A 2D occupancy grid in the world frame.

    Attributes:
        log_odds: ``(H, W)`` float32 log-odds of occupancy; 0 = unknown (p 0.5). Row 0 is the
            lowest y, column 0 the lowest x.
        resolution_m: Cell edge length, metres.
        origin_xy: ``(2,)`` float64 world coordinate (metres) of the lower-left corner of
            cell ``(0, 0)``.
        hits: ``(H, W)`` int32 number of scans with a beam ending in the cell (all zeros
            when the grid was not rendered, e.g. built from an array).
        misses: ``(H, W)`` int32 number of scans with a beam passing through the cell and
            none ending in it (all zeros when the grid was not rendered).
        occupied_thresh: Probability above which a cell is occupied.
        free_thresh: Probability below which a cell is free.
    """

    log_odds: NDArray[np.float32]
    resolution_m: float
    origin_xy: FloatArray
    hits: NDArray[np.int32] = field(default_factory=lambda: _NO_COUNTS)
    misses: NDArray[np.int32] = field(default_factory=lambda: _NO_COUNTS)
    occupied_thresh: float = 0.65
    free_thresh: float = 0.196

    def __post_init__(self) -> None:
        lo = np.asarray(self.log_odds, dtype=np.float32)
        if lo.ndim != 2:
            raise GridError(f"log_odds must be a 2-D (H, W) array, got shape {lo.shape}")
        origin = np.asarray(self.origin_xy, dtype=np.float64).reshape(-1)
        if origin.shape != (2,):
            raise GridError(f"origin_xy must have 2 values (x_m, y_m), got {origin.shape}")
        if not self.resolution_m > 0.0:
            raise GridError(f"resolution_m must be positive, got {self.resolution_m}")
        for name in ("hits", "misses"):
            arr = getattr(self, name)
            if arr is _NO_COUNTS:
                object.__setattr__(self, name, np.zeros(lo.shape, dtype=np.int32))
            elif np.shape(arr) != lo.shape:
                raise GridError(f"{name} has shape {np.shape(arr)}, log_odds {lo.shape}")
        object.__setattr__(self, "log_odds", lo)
        object.__setattr__(self, "origin_xy", origin)

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``: rows (along y) and columns (along x)."""
        return (int(self.log_odds.shape[0]), int(self.log_odds.shape[1]))

    @property
    def extent_xy(self) -> tuple[float, float, float, float]:
        """``(x_min, x_max, y_min, y_max)`` of the grid's outer edges in metres (the
        ``extent`` of ``imshow(..., origin="lower")``)."""
        h, w = self.shape
        ox, oy = self.origin_xy
        return (ox, ox + w * self.resolution_m, oy, oy + h * self.resolution_m)

    def world_to_cell(self, points_xy: ArrayLike) -> NDArray[np.int64]:
        """Cells containing world points.

        Args:
            points_xy: ``(K, 2)`` (or ``(2,)``) float metres, world frame.

        Returns:
            ``(K, 2)`` (or ``(2,)``) int64 ``(row, col)``; a point outside the grid gives
            an index outside ``[0, H) x [0, W)`` (check with :meth:`contains`).
        """
        p = np.asarray(points_xy, dtype=np.float64)
        g = np.floor((p - self.origin_xy) / self.resolution_m).astype(np.int64)
        return g[..., ::-1].copy()

    def cell_to_world(self, cells: ArrayLike) -> FloatArray:
        """World coordinates of cell centres.

        Args:
            cells: ``(K, 2)`` (or ``(2,)``) int ``(row, col)``.

        Returns:
            ``(K, 2)`` (or ``(2,)``) float64 ``(x_m, y_m)`` of the cell centres, world frame.
        """
        rc = np.asarray(cells, dtype=np.float64)
        return (rc[..., ::-1] + 0.5) * self.resolution_m + self.origin_xy

    def contains(self, cells: ArrayLike) -> NDArray[np.bool_]:
        """``(K,)`` bool: which ``(row, col)`` cells ``(K, 2)`` lie inside the grid."""
        rc = np.asarray(cells)
        h, w = self.shape
        return (rc[..., 0] >= 0) & (rc[..., 0] < h) & (rc[..., 1] >= 0) & (rc[..., 1] < w)

    def probabilities(self) -> NDArray[np.float32]:
        """``(H, W)`` float32 occupancy probability ``1 - 1 / (1 + exp(l))``."""
        return (1.0 / (1.0 + np.exp(-self.log_odds))).astype(np.float32)

    def ternary(self) -> NDArray[np.int8]:
        """``(H, W)`` int8 thresholded map as in ROS ``nav_msgs/OccupancyGrid``: -1 unknown,
        0 free (p < free_thresh), 100 occupied (p > occupied_thresh); row 0 = lowest y."""
        p = self.probabilities()
        out = np.full(self.shape, -1, dtype=np.int8)
        out[p < self.free_thresh] = 0
        out[p > self.occupied_thresh] = 100
        return out

    def binary(self) -> NDArray[np.bool_]:
        """``(H, W)`` bool, True where the cell is occupied (p > occupied_thresh)."""
        return self.probabilities() > self.occupied_thresh

    def __repr__(self) -> str:
        t = self.ternary()
        n = max(t.size, 1)
        h, w = self.shape
        x0, x1, y0, y1 = self.extent_xy
        return (
            f"OccupancyGrid({h}x{w} cells at {self.resolution_m:g} m, "
            f"x [{x0:.2f}, {x1:.2f}] m, y [{y0:.2f}, {y1:.2f}] m, "
            f"occupied {np.count_nonzero(t == 100) / n:.1%}, "
            f"free {np.count_nonzero(t == 0) / n:.1%})"
        )


#: Edge length of a storage tile of :class:`TiledGrid`, cells (``2**TILE_SHIFT``).
TILE_SHIFT = 6
TILE_SIZE = 1 << TILE_SHIFT

#: Largest number of tiles a grid's bounds may span (the tile map costs 9 bytes per tile);
#: 2**24 tiles of 64x64 cells are 13 km square at 5 cm.
MAX_TILE_MAP = 2**24


def _ternary_of(log_odds: NDArray[np.float32], occupied: float, free: float) -> NDArray[np.int8]:
    """int8 -1 unknown / 0 free / 100 occupied of log-odds (any shape), as
    :meth:`OccupancyGrid.ternary`."""
    p = (1.0 / (1.0 + np.exp(-log_odds))).astype(np.float32)
    out = np.full(log_odds.shape, -1, dtype=np.int8)
    out[p < free] = 0
    out[p > occupied] = 100
    return out


@dataclass(frozen=True, eq=False)
class TiledGrid:
    """A sparse occupancy grid: only the tiles of ``T x T`` cells (``T`` = :data:`TILE_SIZE`)
    that a beam crossed are stored, so memory follows the area the rays touch, not the
    bounding box (a 400 x 400 m site at 5 cm is 64 M cells dense; its tiles a fraction).

    Cell ``(row, col)`` of the equivalent dense grid (same conventions as
    :class:`OccupancyGrid`: row 0 the lowest y) is ``log_odds[k, row % T, col % T]`` with
    ``k = tile_index[row // T, col // T]``; ``k = -1`` is an untouched tile (unknown,
    log-odds 0, no hits or misses).

    Attributes:
        resolution_m: Cell edge length, metres.
        origin_xy: ``(2,)`` float64 world coordinate (metres) of the lower-left corner of
            cell ``(0, 0)``.
        shape: ``(H, W)`` of the equivalent dense grid.
        tile_index: ``(ceil(H/T), ceil(W/T))`` int64 storage index of each tile, or -1.
        log_odds: ``(K, T, T)`` float32 log-odds of the stored tiles.
        hits: ``(K, T, T)`` int32 scans with a beam ending in the cell.
        misses: ``(K, T, T)`` int32 scans with a beam passing through the cell only.
        occupied_thresh: Probability above which a cell is occupied.
        free_thresh: Probability below which a cell is free.
    """

    resolution_m: float
    origin_xy: FloatArray
    shape: tuple[int, int]
    tile_index: NDArray[np.int64]
    log_odds: NDArray[np.float32]
    hits: NDArray[np.int32]
    misses: NDArray[np.int32]
    occupied_thresh: float = 0.65
    free_thresh: float = 0.196

    @property
    def n_tiles(self) -> int:
        """Number of stored tiles ``K``."""
        return int(self.log_odds.shape[0])

    @property
    def allocated_cells(self) -> int:
        """Cells with storage, ``K * T * T``."""
        return int(self.log_odds.size)

    @property
    def extent_xy(self) -> tuple[float, float, float, float]:
        """``(x_min, x_max, y_min, y_max)`` of the grid's outer edges in metres."""
        h, w = self.shape
        ox, oy = self.origin_xy
        return (ox, ox + w * self.resolution_m, oy, oy + h * self.resolution_m)

    def rows(self, start: int, stop: int, layer: str = "log_odds") -> NDArray[np.generic]:
        """Dense rows ``start:stop`` (full width) of ``log_odds``, ``hits`` or ``misses``.

        Returns:
            ``(stop - start, W)`` array of the layer's dtype (zeros in untouched tiles).
        """
        t = TILE_SIZE
        h, w = self.shape
        start, stop = max(start, 0), min(stop, h)
        data = getattr(self, layer)
        out = np.zeros((max(stop - start, 0), w), dtype=data.dtype)
        for ty in range(start // t, -(-stop // t)):
            r0, r1 = max(start, ty * t), min(stop, (ty + 1) * t)
            for tx in np.flatnonzero(self.tile_index[ty] >= 0).tolist():
                c1 = min(w, (tx + 1) * t)
                tile = data[self.tile_index[ty, tx]]
                out[r0 - start : r1 - start, tx * t : c1] = tile[
                    r0 - ty * t : r1 - ty * t, : c1 - tx * t
                ]
        return out

    def to_dense(self, max_cells: int = 25_000_000) -> OccupancyGrid:
        """The equivalent dense :class:`OccupancyGrid`.

        Raises:
            GridError: it would have more than ``max_cells`` cells.
        """
        h, w = self.shape
        if h * w > max_cells:
            x0, x1, y0, y1 = self.extent_xy
            raise GridError(
                f"the grid would have {h}x{w} = {h * w} cells (x {x0:.1f}..{x1:.1f} m, "
                f"y {y0:.1f}..{y1:.1f} m at {self.resolution_m} m), more than "
                f"max_cells={max_cells}; raise resolution_m, lower range_max_m, or check the "
                "poses for outliers"
            )
        return OccupancyGrid(
            log_odds=self.rows(0, h).astype(np.float32),
            resolution_m=self.resolution_m,
            origin_xy=self.origin_xy,
            hits=self.rows(0, h, "hits").astype(np.int32),
            misses=self.rows(0, h, "misses").astype(np.int32),
            occupied_thresh=self.occupied_thresh,
            free_thresh=self.free_thresh,
        )

    def __repr__(self) -> str:
        h, w = self.shape
        return (
            f"TiledGrid({h}x{w} cells at {self.resolution_m:g} m, {self.n_tiles} tiles of "
            f"{TILE_SIZE}x{TILE_SIZE} stored, {self.allocated_cells / max(h * w, 1):.1%} of dense)"
        )


# ---------------------------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------------------------


def render(
    scans: Sequence[LaserScan],
    poses: ArrayLike,
    config: GridConfig | None = None,
    *,
    range_min_m: float = 0.0,
) -> OccupancyGrid:
    """Render an occupancy grid from scans and one robot pose per scan.

    Each beam is traced from the laser position (pose ∘ laser_offset) to its endpoint; the
    cells it passes are updated with ``l_free`` and the cell it ends in with ``l_occ``, then
    clamped to ``[l_min, l_max]`` (Thrun et al. 2005, ch. 9, Table 9.1-9.2). Each cell is
    updated at most once per scan, as in Table 9.1 (one inverse-sensor-model term per cell
    per measurement ``z_t``): a cell in which any beam of the scan ends is a hit for that
    scan, and is not also marked free by the scan's other beams passing through it.

    Args:
        scans: ``N`` laser scans; their ``laser_offset``, ``range_min_m`` and
            ``range_max_m`` are used; ``odom_pose`` is ignored.
        poses: ``(N, 3)`` float robot poses ``[x_m, y_m, theta_rad]``, robot frame -> world,
            one per scan (e.g. the optimized trajectory).
        config: Grid parameters; defaults to :class:`GridConfig()`.
        range_min_m: A floor on every scan's ``range_min_m``: returns at or within it draw
            nothing (the robot's own body, ``FeatureConfig.robot_body_range_m``).

    Returns:
        The grid, bounded automatically by the poses and the traced beams plus
        ``config.margin_m``; its origin is a multiple of the resolution.

    Raises:
        GridError: pose count differs from the scan count, poses are not ``(N, 3)`` or not
            finite, or the grid would exceed ``config.max_cells``.
    """
    cfg = config or GridConfig()
    return render_tiled(scans, poses, cfg, range_min_m=range_min_m).to_dense(cfg.max_cells)


def render_tiled(
    scans: Sequence[LaserScan],
    poses: ArrayLike,
    config: GridConfig | None = None,
    *,
    range_min_m: float = 0.0,
) -> TiledGrid:
    """:func:`render` into a sparse :class:`TiledGrid`: memory follows the area the beams
    cross (``config.max_cells`` bounds the stored cells), so any real building renders at
    the requested resolution. Same model, same cell values as :func:`render`.

    Raises:
        GridError: as :func:`render`; the stored tiles would exceed ``config.max_cells``, or
            the bounds span more than :data:`MAX_TILE_MAP` tiles (an absurd extent).
    """
    cfg = config or GridConfig()
    p = _check_poses(poses, len(scans))
    if len(scans) == 0:
        return _empty_grid(p, cfg)
    counts = np.array([s.n_beams for s in scans], dtype=np.int64)
    ranges = np.concatenate([s.ranges_m for s in scans])
    angles = np.concatenate([s.angles_rad for s in scans])
    offsets = np.stack([s.laser_offset for s in scans])
    rmin = np.repeat(np.maximum([s.range_min_m for s in scans], range_min_m), counts)
    rmax = np.repeat(np.array([s.range_max_m for s in scans]), counts)
    return _render_flat(p, offsets, counts, ranges, angles, rmin, rmax, cfg)


def render_tiled_beams(
    poses: ArrayLike,
    laser_offsets: FloatArray,
    beam_counts: NDArray[np.int64],
    ranges_m: FloatArray,
    angles_rad: FloatArray,
    range_min_m: FloatArray,
    range_max_m: FloatArray,
    config: GridConfig | None = None,
) -> TiledGrid:
    """:func:`render_tiled` from flattened beams (no per-scan objects; same cell values).

    Args:
        poses: ``(N, 3)`` robot poses, world frame.
        laser_offsets: ``(N, 3)`` laser pose in each robot frame.
        beam_counts: ``(N,)`` int64 beams of each scan; the beam arrays hold scan 0's beams,
            then scan 1's, ...
        ranges_m, angles_rad, range_min_m, range_max_m: ``(B,)`` float64 per beam, laser
            frame, ``B = beam_counts.sum()``.
        config: Grid parameters.

    Raises:
        GridError: as :func:`render_tiled`.
    """
    cfg = config or GridConfig()
    p = _check_poses(poses, int(beam_counts.shape[0]))
    if p.shape[0] == 0:
        return _empty_grid(p, cfg)
    return _render_flat(
        p, laser_offsets, beam_counts, ranges_m, angles_rad, range_min_m, range_max_m, cfg
    )


def render_tiled_chunks(
    poses: ArrayLike,
    chunks: ChunkReader,
    config: GridConfig | None = None,
    chunk_scans: int = CHUNK_SCANS,
    *,
    range_min_m: float = 0.0,
) -> TiledGrid:
    """:func:`render_tiled` in bounded memory: the beams are read and traced in chunks of
    ``chunk_scans`` consecutive scans (same cell values as one pass over all beams).

    The per-beam work arrays (endpoints, cell coordinates, masks: about 100 bytes a beam)
    exist for one chunk at a time, so a long log's grid pass adds a constant to the memory
    of the run instead of a multiple of its beams. Each chunk is read three times (bounds,
    tiles, tracing), except the first and the last, read once.

    Args:
        poses: ``(N, 3)`` robot poses, world frame, one per scan.
        chunks: ``chunks(lo, hi)`` returns the :class:`BeamChunk` of scans ``[lo, hi)``.
        config: Grid parameters.
        chunk_scans: Scans per chunk (>= 1).
        range_min_m: As for :func:`render`.

    Raises:
        GridError: as :func:`render_tiled`.
    """
    cfg = config or GridConfig()
    if range_min_m > 0.0:
        chunks = _with_range_min(chunks, range_min_m)

    p = np.asarray(poses, dtype=np.float64)
    p = _check_poses(p, p.shape[0] if p.ndim == 2 else 0)
    if p.shape[0] == 0:
        return _empty_grid(p, cfg)
    return _render_chunks(p, chunks, cfg, max(1, int(chunk_scans)))


def render_ranges(
    ranges_m: ArrayLike,
    angles_rad: ArrayLike,
    poses: ArrayLike,
    config: GridConfig | None = None,
    *,
    range_min_m: float = 0.0,
    range_max_m: float = math.inf,
    laser_offset: ArrayLike = (0.0, 0.0, 0.0),
) -> OccupancyGrid:
    """Render an occupancy grid from range arrays (same model as :func:`render`).

    Args:
        ranges_m: ``(N, B)`` float beam ranges in metres; a no-return beam holds a value
            ``>= range_max_m`` (or ``inf``); NaN and ``<= range_min_m`` beams are ignored.
        angles_rad: ``(B,)`` or ``(N, B)`` float beam bearings in the laser frame, radians.
        poses: ``(N, 3)`` float robot poses, robot frame -> world.
        config: Grid parameters; defaults to :class:`GridConfig()`.
        range_min_m: A beam is a return only if ``range_min_m < r``.
        range_max_m: ... and ``r < range_max_m`` (the sensor's no-return value).
        laser_offset: ``(3,)`` laser pose in the robot frame ``[x_m, y_m, theta_rad]``.

    Returns:
        The grid (see :func:`render`).

    Raises:
        GridError: inconsistent shapes, non-finite poses, or a grid beyond ``max_cells``.
    """
    cfg = config or GridConfig()
    r = np.asarray(ranges_m, dtype=np.float64)
    if r.ndim != 2:
        raise GridError(f"ranges_m must be (N, B), got shape {r.shape}")
    n, b = r.shape
    p = _check_poses(poses, n)
    a = np.asarray(angles_rad, dtype=np.float64)
    if a.shape == (b,):
        a = np.broadcast_to(a, (n, b))
    if a.shape != (n, b):
        raise GridError(f"angles_rad must be ({b},) or ({n}, {b}), got shape {a.shape}")
    off = np.asarray(laser_offset, dtype=np.float64)
    if off.shape != (3,):
        raise GridError(f"laser_offset must be (3,), got shape {off.shape}")
    if n == 0:
        return _empty_grid(p, cfg).to_dense(cfg.max_cells)
    m = n * b
    return _render_flat(
        p,
        np.broadcast_to(off, (n, 3)),
        np.full(n, b, dtype=np.int64),
        r.reshape(m),
        a.reshape(m),
        np.full(m, range_min_m),
        np.full(m, range_max_m),
        cfg,
    ).to_dense(cfg.max_cells)


def _check_poses(poses: ArrayLike, n_scans: int) -> FloatArray:
    p = np.asarray(poses, dtype=np.float64)
    if p.shape == (0,):
        p = p.reshape(0, 3)
    if p.ndim != 2 or p.shape[1] != 3:
        raise GridError(f"poses must be (N, 3) [x_m, y_m, theta_rad], got shape {p.shape}")
    if p.shape[0] != n_scans:
        raise GridError(f"got {p.shape[0]} poses for {n_scans} scans; pass one pose per scan")
    bad = ~np.all(np.isfinite(p), axis=1)
    if np.any(bad):
        raise GridError(f"pose {int(np.argmax(bad))} is not finite: {p[np.argmax(bad)].tolist()}")
    return p


def _empty_grid(poses: FloatArray, cfg: GridConfig) -> TiledGrid:
    pts = poses[:, :2] if poses.shape[0] else np.zeros((1, 2))
    frame = _frame(pts, cfg)
    n_ty, n_tx = (-(-frame.shape[0] // TILE_SIZE), -(-frame.shape[1] // TILE_SIZE))
    return _tiled_grid(frame, np.full((n_ty, n_tx), -1, dtype=np.int64), cfg)


@dataclass(frozen=True)
class _Frame:
    """The (dense-equivalent) bounds of a grid: origin and ``(H, W)`` in cells."""

    origin: FloatArray
    shape: tuple[int, int]


def _frame(points_xy: FloatArray, cfg: GridConfig) -> _Frame:
    """Bounds covering ``points_xy`` (K, 2) plus the margin. The origin is snapped to a
    multiple of the resolution so grids of one world align."""
    res = cfg.resolution_m
    lo = points_xy.min(axis=0) - cfg.margin_m
    hi = points_xy.max(axis=0) + cfg.margin_m
    origin = np.floor(lo / res) * res
    w, h = (np.floor((hi - origin) / res) + 1).tolist()
    n_tiles = math.ceil(h / TILE_SIZE) * math.ceil(w / TILE_SIZE)
    if not n_tiles <= MAX_TILE_MAP:
        raise GridError(
            f"the map spans x {lo[0]:.1f}..{hi[0]:.1f} m, y {lo[1]:.1f}..{hi[1]:.1f} m: "
            f"{h:.0f}x{w:.0f} cells at {res} m, more than {MAX_TILE_MAP} tiles of "
            f"{TILE_SIZE}x{TILE_SIZE} cells; raise resolution_m, or check the poses for outliers"
        )
    return _Frame(origin, (int(h), int(w)))


def _tiled_grid(frame: _Frame, tile_index: NDArray[np.int64], cfg: GridConfig) -> TiledGrid:
    """An all-unknown tiled grid with storage for the tiles ``tile_index >= 0``."""
    k = int(tile_index.max(initial=-1)) + 1
    cells = k * TILE_SIZE * TILE_SIZE
    if cells > cfg.max_cells:
        h, w = frame.shape
        raise GridError(
            f"the rays touch {k} tiles = {cells} cells of a {h}x{w} grid at "
            f"{cfg.resolution_m} m, more than max_cells={cfg.max_cells}; raise resolution_m, "
            "lower range_max_m, or check the poses for outliers"
        )
    tiles = (k, TILE_SIZE, TILE_SIZE)
    return TiledGrid(
        resolution_m=cfg.resolution_m,
        origin_xy=frame.origin,
        shape=frame.shape,
        tile_index=tile_index,
        log_odds=np.zeros(tiles, dtype=np.float32),
        hits=np.zeros(tiles, dtype=np.int32),
        misses=np.zeros(tiles, dtype=np.int32),
        occupied_thresh=cfg.occupied_thresh,
        free_thresh=cfg.free_thresh,
    )


def _render_flat(
    poses: FloatArray,
    laser_offsets: FloatArray,
    beam_counts: NDArray[np.int64],
    ranges: FloatArray,
    angles: FloatArray,
    range_min: FloatArray,
    range_max: FloatArray,
    cfg: GridConfig,
) -> TiledGrid:
    """Shared body of :func:`render_tiled` and :func:`render_ranges` on flattened beams."""
    chunk = BeamChunk(laser_offsets, beam_counts, ranges, angles, range_min, range_max)
    return _render_chunks(poses, lambda lo, hi: chunk, cfg, chunk_scans=poses.shape[0])


def _render_chunks(
    poses: FloatArray, chunks: ChunkReader, cfg: GridConfig, chunk_scans: int
) -> TiledGrid:
    """Render in passes over chunks of whole scans: bounds, tiles, then tracing.

    Each pass rebuilds a chunk's beams (:func:`_chunk_beams`), so the per-beam work arrays
    live for a few chunks at a time; the bounds are the min/max over chunks and the tracer
    processes the scans in order, so the cells are the same as in one pass over all beams.
    The passes reuse what they can: the bounds pass keeps the first and the last chunk's
    beams (endpoints in the world, ~17 bytes a beam), the tile pass runs from the last chunk
    to the first (marking tiles does not depend on the order), so the tracer starts on the
    chunk it walked last and ends on a kept one. A log of one or two chunks is read once.
    """
    # the cores watched through the passes before the tracing (CoreWatch), not in a wait
    watch = CoreWatch() if not cfg.threads else None
    n = poses.shape[0]
    spans = [(lo, min(lo + chunk_scans, n)) for lo in range(0, n, max(1, chunk_scans))]
    lo_xy = np.full(2, np.inf)
    hi_xy = np.full(2, -np.inf)
    n_traced = n_hits = 0
    # The first and last chunks' beams stay (the tile pass ends on the first, the tracing
    # starts there and ends on the last): two chunks of endpoints, a constant.
    kept: dict[tuple[int, int], _ChunkBeams] = {}
    for a, b in spans:
        beams = _chunk_beams(poses[a:b], chunks(a, b), cfg)
        if (a, b) in (spans[0], spans[-1]):
            kept[(a, b)] = beams
        for pts in (beams.end, beams.laser_xy, poses[a:b, :2]):
            if pts.shape[0]:  # column by column: numpy reduces (K, 2) along axis 0 slowly
                lo_xy = np.minimum(lo_xy, [pts[:, 0].min(), pts[:, 1].min()])
                hi_xy = np.maximum(hi_xy, [pts[:, 0].max(), pts[:, 1].max()])
        n_traced += beams.end.shape[0]
        n_hits += int(np.count_nonzero(beams.is_hit))
    frame = _frame(np.stack([lo_xy, hi_xy]), cfg)

    @functools.lru_cache(maxsize=1)
    def walk(a: int, b: int) -> _Beams:
        world = kept.get((a, b))
        if world is None:
            world = _chunk_beams(poses[a:b], chunks(a, b), cfg)
        return _grid_beams(world, frame, cfg.resolution_m)

    threads = cfg.threads if watch is None else watch.workers()
    grid = _trace_tiled(frame, spans, walk, cfg, threads, exact=False)
    if grid is None:  # the tile walk missed a tile a cell walk reaches: walk cell by cell
        grid = _trace_tiled(frame, spans, walk, cfg, threads, exact=True)
        assert grid is not None
    if cfg.mode == "binary":
        _binarize(grid, cfg)
    logger.debug(
        "rendered %d scans, %d beams traced (%d hits) into %d tiles of a %dx%d grid",
        *(n, n_traced, n_hits, grid.n_tiles, *frame.shape),
    )
    return grid


class BeamChunk(NamedTuple):
    """Flattened beams of a run of consecutive scans (for :func:`render_tiled_chunks`).

    Attributes:
        laser_offsets: ``(n, 3)`` laser pose in each robot frame.
        beam_counts: ``(n,)`` int64 beams of each scan; the beam arrays hold the first scan's
            beams, then the next scan's, ...
        ranges_m, angles_rad, range_min_m, range_max_m: ``(B,)`` float64 per beam, laser
            frame, ``B = beam_counts.sum()``.
    """

    laser_offsets: FloatArray
    beam_counts: NDArray[np.int64]
    ranges_m: FloatArray
    angles_rad: FloatArray
    range_min_m: FloatArray
    range_max_m: FloatArray


#: Reads the beams of scans ``[lo, hi)`` (a :class:`BeamChunk`).
ChunkReader = Callable[[int, int], BeamChunk]


def _with_range_min(chunks: ChunkReader, range_min_m: float) -> ChunkReader:
    """``chunks`` with every beam's ``range_min_m`` at least ``range_min_m``."""

    def read(lo: int, hi: int) -> BeamChunk:
        c = chunks(lo, hi)
        return c._replace(range_min_m=np.maximum(c.range_min_m, range_min_m))

    return read


class _ChunkBeams(NamedTuple):
    """One chunk's traced beams in the world (the tracer's input before the grid frame)."""

    end: FloatArray  # (K, 2) endpoints
    laser_xy: FloatArray  # (n, 2) laser positions
    scan_start: NDArray[np.int64]  # (n + 1,) beams of scan s: scan_start[s]:scan_start[s + 1]
    is_hit: NDArray[np.bool_]  # (K,)


def _chunk_beams(poses: FloatArray, chunk: BeamChunk, cfg: GridConfig) -> _ChunkBeams:
    """The beams of one chunk to trace (hits, and no-returns cleared up to
    ``no_return_clear_m``) in the world: endpoints and laser positions."""
    n = poses.shape[0]
    ranges, angles = chunk.ranges_m, chunk.angles_rad
    scan_of_beam = np.repeat(np.arange(n), chunk.beam_counts)
    laser = compose(poses, chunk.laser_offsets)  # (n, 3) laser pose in the world
    rmax = chunk.range_max_m
    if cfg.range_max_m is not None:
        rmax = np.minimum(rmax, cfg.range_max_m)
    with np.errstate(invalid="ignore"):
        is_hit = np.isfinite(ranges) & (ranges > chunk.range_min_m) & (ranges < rmax)
        no_return = ranges >= rmax  # inf included, NaN excluded
    length = np.where(is_hit, ranges, 0.0)
    traced = is_hit.copy()
    if cfg.no_return_clear_m is not None:
        length = np.where(no_return, np.minimum(ranges, cfg.no_return_clear_m), length)
        traced |= no_return
    keep = np.flatnonzero(traced)
    s = scan_of_beam[keep]
    bearing = laser[s, 2] + angles[keep]
    length = length[keep]
    # column by column: the same values as on (K, 2) arrays, without their temporaries
    end = np.empty((keep.shape[0], 2))
    np.add(laser[s, 0], length * np.cos(bearing), out=end[:, 0])
    np.add(laser[s, 1], length * np.sin(bearing), out=end[:, 1])
    scan_start = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(s, minlength=n), out=scan_start[1:])
    return _ChunkBeams(end, laser[:, :2], scan_start, is_hit[keep])


def _grid_beams(beams: _ChunkBeams, frame: _Frame, res: float) -> _Beams:
    """A chunk's beams in the continuous cell coordinates ``(col, row)`` of ``frame``. The
    clip only absorbs floating-point rounding at the grid's edges (the bounds contain every
    point): the compiled loops do not check them."""
    h, w = frame.shape
    upper = np.nextafter(np.array([w, h], dtype=np.float64), 0.0)
    origin_g = np.clip((beams.laser_xy - frame.origin) / res, 0.0, upper)
    end_g = np.empty_like(beams.end)
    for axis in (0, 1):
        cells = np.subtract(beams.end[:, axis], frame.origin[axis], out=end_g[:, axis])
        np.clip(np.divide(cells, res, out=cells), 0.0, upper[axis], out=cells)
    return _Beams(beams.scan_start, origin_g, end_g, beams.is_hit)


class _Beams(NamedTuple):
    """Beams in continuous cell coordinates (see :func:`_trace_scans`)."""

    scan_start: NDArray[np.int64]
    origin_g: FloatArray
    end_g: FloatArray
    is_hit: NDArray[np.bool_]


def _trace_tiled(
    frame: _Frame,
    spans: list[tuple[int, int]],
    walk: Callable[[int, int], _Beams],
    cfg: GridConfig,
    threads: int,
    exact: bool,
) -> TiledGrid | None:
    """Allocate the tiles the beams cross and trace them, chunk by chunk (``walk(lo, hi)``
    gives the beams of scans ``[lo, hi)``) in ``threads`` threads. The tile marking walks tile
    by tile, or cell by cell when ``exact``; None when the tile walk missed a tile the cell
    walk reaches (a segment through a tile corner within rounding)."""
    h, w = frame.shape
    tile_mask = np.zeros((-(-h // TILE_SIZE), -(-w // TILE_SIZE)), dtype=np.bool_)
    unit = 0 if exact else TILE_SHIFT
    for a, b in reversed(spans):  # the tracer then starts on the chunk walked last
        beams = walk(a, b)
        _mark_tiles(beams.scan_start, beams.origin_g, beams.end_g, unit, TILE_SHIFT, tile_mask)
    order = np.cumsum(tile_mask.reshape(-1)).reshape(tile_mask.shape) - 1
    grid = _tiled_grid(frame, np.where(tile_mask, order, -1), cfg)
    model = InverseSensorModel(cfg.l_occ, cfg.l_free, cfg.l_min, cfg.l_max)
    missing = 0
    with ThreadPoolExecutor(threads) as pool:
        for a, b in spans:
            beams = walk(a, b)
            bands = _row_bands(beams, threads, tile_mask.shape[0])
            stamp = np.full(grid.log_odds.size, -1, dtype=np.int64)  # shared: disjoint cells

            def trace(band: tuple[int, int], beams: _Beams = beams, stamp: NDArray = stamp) -> int:
                return int(
                    _trace_scans(
                        *beams,
                        grid.tile_index,
                        TILE_SHIFT,
                        *band,
                        model,
                        grid.log_odds.reshape(-1),
                        grid.hits.reshape(-1),
                        grid.misses.reshape(-1),
                        stamp,
                    )
                )

            missing += sum(pool.map(trace, bands))
    if missing:
        logger.debug("tile walk missed %d cell visits; marking tiles cell by cell", missing)
        return None
    return grid


def _row_bands(beams: _Beams, n: int, rows: int) -> list[tuple[int, int]]:
    """Up to ``n`` bands ``[first, stop)`` of the ``rows`` tile rows, covering them all, each
    holding about the same number of the beams' endpoints (a stand-in for the cells they
    cross), for :func:`_trace_scans` threads."""
    if n <= 1:
        return [(0, rows)]
    ends = np.bincount(beams.end_g[:, 1].astype(np.int64) >> TILE_SHIFT, minlength=rows)
    per_row = np.cumsum(ends)
    cuts = np.searchsorted(per_row, per_row[-1] * np.arange(1, n) / n, side="right")
    edges = np.unique(np.concatenate([[0], cuts, [rows]]))
    return list(itertools.pairwise(edges.tolist()))


def _binarize(grid: OccupancyGrid | TiledGrid, cfg: GridConfig) -> None:
    """The paper's binary map (§IV, Fig. 3-4), from per-scan hit and miss counts: occupied
    (log-odds l_max) if ``hits >= 1 and hits >= misses``, free (l_min) if ``misses > hits``,
    unknown (0) if no ray reached the cell."""
    hits, misses = grid.hits, grid.misses
    occupied = (hits > 0) & (hits >= misses)
    free = misses > hits
    grid.log_odds[...] = np.where(occupied, cfg.l_max, np.where(free, cfg.l_min, 0.0))


class InverseSensorModel(NamedTuple):
    """Log-odds terms of the inverse range sensor model (Thrun et al. 2005, Table 9.2) and
    the clamping limits (OctoMap, Hornung et al. 2013), grouped for the compiled tracer."""

    l_occ: float
    l_free: float
    l_min: float
    l_max: float


@njit(cache=True, inline="always")
def _axis_start(p0: float, i0: int, d: float) -> tuple[int, float, float]:
    """Amanatides & Woo (1987) set-up along one axis, in cell units: the step direction,
    the ray parameter per cell, and the parameter of the first cell boundary."""
    if d > 0.0:
        t_delta = 1.0 / d
        return 1, t_delta, (i0 + 1 - p0) * t_delta
    if d < 0.0:
        t_delta = -1.0 / d
        return -1, t_delta, (p0 - i0) * t_delta
    return 0, math.inf, math.inf


@njit(cache=True, inline="always")
def _next_cell(
    ix: int,
    iy: int,
    ix_end: int,
    iy_end: int,
    step_x: int,
    step_y: int,
    t_max_x: float,
    t_max_y: float,
    t_delta_x: float,
    t_delta_y: float,
) -> tuple[int, int, float, float]:
    """One Amanatides–Woo step: to the neighbour cell whose boundary the ray crosses first
    (in y on a tie; never past the end cell's column or row)."""
    if ix == ix_end or (iy != iy_end and t_max_y <= t_max_x):
        return ix, iy + step_y, t_max_x, t_max_y + t_delta_y
    return ix + step_x, iy, t_max_x + t_delta_x, t_max_y


@njit(cache=True, inline="always")
def _cell(tile_index: NDArray[np.int64], shift: int, ix: int, iy: int) -> int:
    """Flat storage index of cell (column ``ix``, row ``iy``; both >= 0) in the tiled arrays
    (tiles of ``2**shift`` cells on a side), or -1 when its tile has no storage."""
    tile = tile_index[iy >> shift, ix >> shift]
    if tile < 0:
        return -1
    mask = (1 << shift) - 1
    return ((tile << shift) + (iy & mask) << shift) + (ix & mask)


@njit(cache=True, nogil=True)
def _mark_tiles(
    scan_start: NDArray[np.int64],
    origin_g: FloatArray,
    end_g: FloatArray,
    unit_shift: int,
    tile_shift: int,
    tile_mask: NDArray[np.bool_],
) -> None:  # pragma: no cover - compiled
    """Mark the tiles (``2**tile_shift`` cells on a side) every beam crosses, endpoint
    included, by the Amanatides & Woo (1987) walk of :func:`_trace_scans` on a grid of
    ``2**unit_shift`` cells: ``unit_shift = tile_shift`` walks tile by tile (fast), and
    ``unit_shift = 0`` cell by cell, exactly the cells the tracer updates."""
    scale = 1.0 / (1 << unit_shift)  # a power of two: the scaled coordinates are exact
    up = tile_shift - unit_shift
    for s in range(scan_start.shape[0] - 1):
        x0 = origin_g[s, 0] * scale
        y0 = origin_g[s, 1] * scale
        ix0 = math.floor(x0)
        iy0 = math.floor(y0)
        for b in range(scan_start[s], scan_start[s + 1]):
            x1 = end_g[b, 0] * scale
            y1 = end_g[b, 1] * scale
            ix_end = math.floor(x1)
            iy_end = math.floor(y1)
            step_x, t_delta_x, t_max_x = _axis_start(x0, ix0, x1 - x0)
            step_y, t_delta_y, t_max_y = _axis_start(y0, iy0, y1 - y0)
            ix = ix0
            iy = iy0
            n_steps = abs(ix_end - ix0) + abs(iy_end - iy0)
            for k in range(n_steps + 1):
                tile_mask[iy >> up, ix >> up] = True
                if k == n_steps:
                    break
                ix, iy, t_max_x, t_max_y = _next_cell(
                    ix, iy, ix_end, iy_end, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y
                )


@njit(cache=True, nogil=True)
def _trace_scans(
    scan_start: NDArray[np.int64],
    origin_g: FloatArray,
    end_g: FloatArray,
    is_hit: NDArray[np.bool_],
    tile_index: NDArray[np.int64],
    tile_shift: int,
    band_first: int,
    band_stop: int,
    model: InverseSensorModel,
    log_odds: NDArray[np.float32],
    hits: NDArray[np.int32],
    misses: NDArray[np.int32],
    stamp: NDArray[np.int64],
) -> int:  # pragma: no cover - compiled
    """Trace every beam of every scan through the tiled grid (in place), updating only the
    cells in tile rows ``band_first <= row < band_stop``; return the number of those cell
    visits that found no storage (0 unless the tile marking missed a tile). Threads on
    disjoint bands share the arrays: each cell is updated by one of them, in scan order.

    Coordinates are continuous cell units ``(x - ox) / res`` (column) and ``(y - oy) / res``
    (row). Beams of scan ``s`` are ``scan_start[s]:scan_start[s+1]``. Storage is tiled: cell
    ``(row, col)`` lives in tile ``tile_index[row // T, col // T]`` (``T = 2**tile_shift``;
    every tile a beam crosses is allocated, see :func:`_mark_tiles`). A per-cell ``stamp``
    (``-1`` initially) holds ``2 s + 1`` once scan ``s`` hit the cell and ``2 s`` once it
    marked it free, so each cell is updated at most once per scan, hits first (they take
    precedence). Cells along a beam are enumerated exactly (every cell the segment crosses)
    by the Amanatides & Woo (1987) traversal, stepping exactly ``|dcol| + |drow|`` times so
    it ends in the endpoint cell.
    """
    l_occ, l_free, l_min, l_max = model
    mask = (1 << tile_shift) - 1
    missing = 0
    n_scans = scan_start.shape[0] - 1
    for s in range(n_scans):
        b0 = scan_start[s]
        b1 = scan_start[s + 1]
        hit_mark = 2 * s + 1
        free_mark = 2 * s
        for b in range(b0, b1):
            row = math.floor(end_g[b, 1])
            if is_hit[b] and band_first <= row >> tile_shift < band_stop:
                c = _cell(tile_index, tile_shift, math.floor(end_g[b, 0]), row)
                if c < 0:
                    missing += 1
                elif stamp[c] != hit_mark:
                    stamp[c] = hit_mark
                    hits[c] += 1
                    v = log_odds[c] + l_occ
                    log_odds[c] = v if v < l_max else l_max
        x0 = origin_g[s, 0]
        y0 = origin_g[s, 1]
        ix0 = math.floor(x0)
        iy0 = math.floor(y0)
        for b in range(b0, b1):
            x1 = end_g[b, 0]
            y1 = end_g[b, 1]
            ix_end = math.floor(x1)
            iy_end = math.floor(y1)
            if (
                max(iy0, iy_end) >> tile_shift < band_first
                or min(iy0, iy_end) >> tile_shift >= band_stop
            ):
                continue  # the beam's rows (from iy0 to iy_end) miss the band
            dx = x1 - x0
            dy = y1 - y0
            step_x, t_delta_x, t_max_x = _axis_start(x0, ix0, dx)
            step_y, t_delta_y, t_max_y = _axis_start(y0, iy0, dy)
            ix = ix0
            iy = iy0
            n_steps = abs(ix_end - ix0) + abs(iy_end - iy0)
            last_free = n_steps - 1 if is_hit[b] else n_steps
            tile_row = -1
            tile_col = -1
            base = -1
            in_band = False
            for k in range(last_free + 1):
                if iy >> tile_shift != tile_row or ix >> tile_shift != tile_col:
                    tile_row = iy >> tile_shift
                    tile_col = ix >> tile_shift
                    in_band = band_first <= tile_row < band_stop
                    base = tile_index[tile_row, tile_col] << (2 * tile_shift)
                c = base + ((iy & mask) << tile_shift) + (ix & mask)
                if not in_band:
                    pass
                elif base < 0:
                    missing += 1
                elif stamp[c] < free_mark:
                    stamp[c] = free_mark
                    misses[c] += 1
                    v = log_odds[c] + l_free
                    log_odds[c] = v if v > l_min else l_min
                if k == n_steps:
                    break
                ix, iy, t_max_x, t_max_y = _next_cell(
                    ix, iy, ix_end, iy_end, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y
                )
    return missing


# ---------------------------------------------------------------------------------------------
# Export
# ---------------------------------------------------------------------------------------------


def _log_odds_rows(grid: OccupancyGrid | TiledGrid, start: int, stop: int) -> NDArray[np.float32]:
    if isinstance(grid, TiledGrid):
        return grid.rows(start, stop).astype(np.float32, copy=False)
    return grid.log_odds[start:stop]


#: Rows per block when an export walks a grid (bounds the memory of a large map's export).
_EXPORT_ROWS = 512


def _top_down_blocks(h: int) -> list[tuple[int, int]]:
    """Row ranges ``(start, stop)`` of height ``_EXPORT_ROWS`` from the top (highest y) down."""
    return [(max(0, stop - _EXPORT_ROWS), stop) for stop in range(h, 0, -_EXPORT_ROWS)]


def write_map_server(grid: OccupancyGrid | TiledGrid, path_stem: str | Path) -> tuple[Path, Path]:
    """Write the ROS map_server pair ``<path_stem>.pgm`` and ``<path_stem>.yaml`` atomically.

    The PGM is binary (P5), one byte per cell, rows top-down (highest y first): 0 occupied,
    254 free, 205 unknown (:meth:`OccupancyGrid.ternary`). The YAML holds ``image`` (the
    PGM's file name, relative to the YAML), ``resolution`` (m/cell), ``origin``
    ``[x_m, y_m, 0.0]`` (world pose of the lower-left pixel's corner), ``negate: 0``,
    ``occupied_thresh``, ``free_thresh`` and ``mode: trinary``. A :class:`TiledGrid` is
    written block by block of rows (its dense image is never held in memory).

    Args:
        grid: The map.
        path_stem: Output path without suffix; its directory must exist.

    Returns:
        ``(pgm_path, yaml_path)``.

    Raises:
        GridError: the files cannot be written.
    """
    stem = Path(path_stem)
    pgm_path = stem.parent / f"{stem.name}.pgm"
    yaml_path = stem.parent / f"{stem.name}.yaml"
    h, w = grid.shape
    meta = {
        "image": pgm_path.name,
        "resolution": float(grid.resolution_m),
        "origin": [float(grid.origin_xy[0]), float(grid.origin_xy[1]), 0.0],
        "negate": 0,
        "occupied_thresh": float(grid.occupied_thresh),
        "free_thresh": float(grid.free_thresh),
        "mode": "trinary",
    }
    try:
        with atomic_write(pgm_path, "wb") as fh:
            fh.write(b"P5\n%d %d\n255\n" % (w, h))
            for start, stop in _top_down_blocks(h):
                t = _ternary_of(
                    _log_odds_rows(grid, start, stop), grid.occupied_thresh, grid.free_thresh
                )
                img = np.full(t.shape, PGM_UNKNOWN, dtype=np.uint8)
                img[t == 0] = PGM_FREE
                img[t == 100] = PGM_OCCUPIED
                fh.write(np.ascontiguousarray(img[::-1]).tobytes())
        with atomic_write(yaml_path, "w") as fh:
            yaml.safe_dump(meta, fh, sort_keys=False, default_flow_style=None)
    except OSError as exc:
        raise GridError(f"cannot write the map_server pair {stem}.pgm/.yaml: {exc}") from exc
    return pgm_path, yaml_path


def _preview_grey(
    grid: OccupancyGrid | TiledGrid, max_pixels: int
) -> tuple[NDArray[np.uint8], int]:
    """Grey image ``255 * (1 - p)`` top-down, reduced by an integer factor ``f`` (darkest cell
    of each ``f x f`` block, so walls survive) until it has at most ``max_pixels``."""
    h, w = grid.shape
    f = max(1, math.ceil(math.sqrt(h * w / max_pixels)))
    hf, wf = -(-h // f), -(-w // f)
    out = np.empty((hf, wf), dtype=np.uint8)
    step = max(1, _EXPORT_ROWS // f) * f
    for start in range(0, h, step):
        lo = _log_odds_rows(grid, start, min(h, start + step))
        p = (1.0 / (1.0 + np.exp(-lo))).astype(np.float32)
        grey = np.round(255.0 * (1.0 - p)).astype(np.uint8)
        rb, cb = -(-grey.shape[0] // f), wf
        padded = np.full((rb * f, cb * f), 255, dtype=np.uint8)
        padded[: grey.shape[0], :w] = grey
        out[start // f : start // f + rb] = padded.reshape(rb, f, cb, f).min(axis=(1, 3))
    return out[::-1], f


#: Largest PNG preview, pixels; a larger grid is reduced by an integer factor.
PNG_MAX_PIXELS = 25_000_000
#: The PNG's colours of the trajectory and of its first pose (RGB).
TRAJECTORY_RGB = (220, 30, 30)
START_RGB = (0, 160, 0)


def write_png(
    grid: OccupancyGrid | TiledGrid, path: str | Path, trajectory: ArrayLike | None = None
) -> Path:
    """Write the probability map as a PNG, one pixel per cell, with the trajectory over it.

    Grey level ``255 * (1 - p)`` (white free, black occupied, mid-grey unknown), rows
    top-down (highest y first); the trajectory is drawn in red and its first pose as a green
    dot (:data:`TRAJECTORY_RGB`, :data:`START_RGB`). A grid of more than
    :data:`PNG_MAX_PIXELS` cells is reduced by the smallest integer factor ``f`` that fits
    (each pixel the darkest of ``f x f`` cells); the map_server PGM always keeps the full
    resolution. The PNG is a palette image (one byte a pixel: :func:`_preview_image`), or
    RGB where the map uses every grey level; either way the same colours.

    Args:
        grid: The map.
        path: Output file (``.png``); its directory must exist.
        trajectory: ``(N, 2+)`` float world positions ``[x_m, y_m, ...]``, or ``None``.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        GridError: the trajectory is not ``(N, 2+)``, or the file cannot be written.
    """
    from PIL import ImageDraw

    out = Path(path)
    grey, f = _preview_grey(grid, PNG_MAX_PIXELS)
    img, line_fill, start_fill = _preview_image(grey)
    if trajectory is not None:
        t = np.asarray(trajectory, dtype=np.float64)
        if t.ndim != 2 or t.shape[1] < 2:
            raise GridError(f"trajectory must be (N, 2) or (N, 3), got shape {t.shape}")
        if t.shape[0] > 0:
            h = grid.shape[0]
            res = grid.resolution_m * f
            px = (t[:, 0] - grid.origin_xy[0]) / res
            py = h / f - (t[:, 1] - grid.origin_xy[1]) / res
            draw = ImageDraw.Draw(img)
            pts = list(zip(px.tolist(), py.tolist(), strict=True))
            if len(pts) > 1:
                draw.line(pts, fill=line_fill, width=1)
            r = 3
            draw.ellipse(
                (pts[0][0] - r, pts[0][1] - r, pts[0][0] + r, pts[0][1] + r), fill=start_fill
            )
    try:
        with atomic_path(out) as tmp:
            img.save(tmp, format="PNG")
    except OSError as exc:
        raise GridError(f"cannot write {out}: {exc}") from exc
    return out


def _preview_image(
    grey: NDArray[np.uint8],
) -> tuple[Image.Image, int | tuple[int, int, int], int | tuple[int, int, int]]:
    """The ``(H, W)`` uint8 grey preview as an image to draw on, with the fills that draw
    :data:`TRAJECTORY_RGB` and :data:`START_RGB` on it: a palette image whose palette maps
    every grey level to itself and two levels the preview does not use to those colours
    (the fills are their indices), or, where it uses every level, an RGB image. A palette
    PNG holds one byte a pixel against three: on a map of real logs it is written in about
    half the time and is half the size, every pixel the same colour."""
    from PIL import Image

    pixels = np.ascontiguousarray(grey)
    unused = np.flatnonzero(np.bincount(pixels.reshape(-1), minlength=256) == 0)
    if unused.shape[0] < 2:
        return Image.fromarray(pixels, mode="L").convert("RGB"), TRAJECTORY_RGB, START_RGB
    line_index, start_index = int(unused[0]), int(unused[1])
    palette = np.repeat(np.arange(256, dtype=np.uint8)[:, None], 3, axis=1)
    palette[line_index], palette[start_index] = TRAJECTORY_RGB, START_RGB
    img = Image.fromarray(pixels, mode="L")
    img.putpalette(palette.reshape(-1).tobytes())  # an "L" image becomes "P"
    return img, line_index, start_index


def write_npz(grid: OccupancyGrid, path: str | Path) -> Path:
    """Write the grid's arrays to a compressed numpy archive, atomically.

    Keys: ``log_odds`` (H, W) float32, ``hits`` and ``misses`` (H, W) int32,
    ``resolution_m`` (), ``origin_xy`` (2,) float64,
    ``occupied_thresh`` and ``free_thresh`` (). Row 0 is the lowest y.

    Args:
        grid: The map.
        path: Output file (``.npz``); its directory must exist.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        GridError: the file cannot be written.
    """
    out = Path(path)
    arrays: dict[str, NDArray[np.generic]] = {
        "log_odds": grid.log_odds,
        "resolution_m": np.float64(grid.resolution_m),
        "origin_xy": grid.origin_xy,
        "occupied_thresh": np.float64(grid.occupied_thresh),
        "free_thresh": np.float64(grid.free_thresh),
        "hits": grid.hits,
        "misses": grid.misses,
    }
    try:
        with atomic_write(out, "wb") as fh:
            np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]
    except OSError as exc:
        raise GridError(f"cannot write {out}: {exc}") from exc
    return out
