"""Tests of ``iceg.grid`` (occupancy grid) and ``iceg.plot.grid``.

Truth comes from hand-computed cell indices and log-odds sums, from the simulator's wall
segments (rasterized here into the same grid) and its exact ray caster, and from the
corrected real logs ``aces-corrected.log.gz`` and ``csail.log`` with a geometric proxy for
"single, straight walls" and a perturbed-pose control that must fail it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.image import AxesImage
from matplotlib.lines import Line2D
from numpy.typing import NDArray
from PIL import Image
from pydantic import ValidationError
from scipy import ndimage

from frontends import open_log
from frontends.scan import LaserScan
from frontends.simulate import World, office_world, ray_ranges, rectangle, simulate
from iceg import grid as grid_module
from iceg import plot
from iceg.grid import (
    GridConfig,
    GridError,
    OccupancyGrid,
    render,
    render_ranges,
    render_tiled,
    render_tiled_chunks,
    write_map_server,
    write_npz,
    write_png,
)
from iceg.scan_store import ScanStore
from iceg_common.se2 import compose
from tests.conftest import shared_file

CFG = GridConfig()
L_OCC, L_FREE, L_MIN, L_MAX = CFG.l_occ, CFG.l_free, CFG.l_min, CFG.l_max
NEIGHBOURS_3X3 = np.ones((3, 3), dtype=bool)


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------


def rasterize_walls(grid: OccupancyGrid, walls: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Ground-truth wall cells: every cell a wall segment (W, 2, 2) passes through, found by
    sampling each segment every resolution/8."""
    truth = np.zeros(grid.shape, dtype=bool)
    for a, b in walls:
        n = math.ceil(np.linalg.norm(b - a) / (grid.resolution_m / 8.0)) + 1
        pts = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
        rc = grid.world_to_cell(pts)
        rc = rc[grid.contains(rc)]
        truth[rc[:, 0], rc[:, 1]] = True
    return truth


def visible_wall_cells(
    grid: OccupancyGrid,
    scans: list[LaserScan],
    poses: NDArray[np.float64],
    walls: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """Cells of the exact (noise-free) beam endpoints: the wall cells the laser could see."""
    seen = np.zeros(grid.shape, dtype=bool)
    for scan, pose in zip(scans, poses, strict=True):
        laser = compose(pose, scan.laser_offset)
        bearing = laser[2] + scan.angles_rad
        r = ray_ranges(laser[:2], bearing, walls)
        ok = r < scan.range_max_m
        end = laser[:2] + r[ok, None] * np.stack([np.cos(bearing[ok]), np.sin(bearing[ok])], 1)
        rc = grid.world_to_cell(end)
        seen[rc[:, 0], rc[:, 1]] = True
    return seen


def occupancy_scores(
    grid: OccupancyGrid,
    walls: NDArray[np.float64],
    scans: list[LaserScan],
    poses: NDArray[np.float64],
) -> tuple[float, float, float]:
    """(precision, recall, free fraction) against the rasterized walls, within one cell."""
    truth = rasterize_walls(grid, walls)
    near_truth = ndimage.binary_dilation(truth, NEIGHBOURS_3X3)
    ternary = grid.ternary()
    occupied = ternary == 100
    precision = np.count_nonzero(occupied & near_truth) / max(int(np.count_nonzero(occupied)), 1)
    seen = visible_wall_cells(grid, scans, poses, walls)
    near_occupied = ndimage.binary_dilation(occupied, NEIGHBOURS_3X3)
    recall = np.count_nonzero(seen & near_occupied) / np.count_nonzero(seen)
    passed_free = (grid.misses > 0) & ~near_truth  # truly free cells some ray passed through
    free_fraction = np.count_nonzero(passed_free & (ternary == 0)) / np.count_nonzero(passed_free)
    return precision, recall, free_fraction


def isolated_fraction(grid: OccupancyGrid) -> float:
    """Fraction of occupied cells with no occupied cell among their 8 neighbours."""
    occ = grid.ternary() == 100
    nb = ndimage.convolve(occ.astype(np.int32), np.ones((3, 3), np.int32), mode="constant") - 1
    return np.count_nonzero(occ & (nb == 0)) / max(int(np.count_nonzero(occ)), 1)


def local_wall_thickness_cells(grid: OccupancyGrid, radius: int = 4) -> NDArray[np.float64]:
    """Per occupied cell: RMS distance (cells) of the occupied cells within a (2r+1)^2 window
    from their best-fit line, sqrt of the covariance's smaller eigenvalue (cells with fewer
    than 6 occupied neighbours in the window are skipped).

    A single straight wall rasterizes into a band one or two cells wide: 0 to 0.5 cell
    (a two-cell band has its centres at +-0.5). A doubled or smeared wall (copies >= 2 cells
    apart) gives >= 1 cell.
    """
    occ = (grid.ternary() == 100).astype(np.float64)
    rows, cols = np.mgrid[0 : occ.shape[0], 0 : occ.shape[1]].astype(np.float64)
    k = 2 * radius + 1

    def window_sum(a: NDArray[np.float64]) -> NDArray[np.float64]:
        return ndimage.uniform_filter(a, k, mode="constant") * (k * k)

    n = window_sum(occ)
    keep = (occ > 0) & (n > 5.5)
    n = n[keep]
    mx, my = window_sum(occ * cols)[keep] / n, window_sum(occ * rows)[keep] / n
    cxx = window_sum(occ * cols * cols)[keep] / n - mx * mx
    cyy = window_sum(occ * rows * rows)[keep] / n - my * my
    cxy = window_sum(occ * cols * rows)[keep] / n - mx * my
    half_trace = 0.5 * (cxx + cyy)
    lam_min = half_trace - np.sqrt(np.maximum(half_trace**2 - (cxx * cyy - cxy**2), 0.0))
    return np.sqrt(np.maximum(lam_min, 0.0))


def beam_grid(ranges, angles, poses, **cfg: object) -> OccupancyGrid:
    """Render with 0.1 m cells and no margin (small hand-checkable grids)."""
    config = GridConfig(resolution_m=0.1, margin_m=0.0, **cfg)  # type: ignore[arg-type]
    return render_ranges(ranges, angles, poses, config, range_max_m=20.0)


@pytest.fixture(scope="module")
def office_run():
    return simulate(office_world(), seed=0)


# ---------------------------------------------------------------------------------------------
# ray model, hand-computed
# ---------------------------------------------------------------------------------------------


def test_single_beam_marks_cells_free_and_endpoint_occupied() -> None:
    # Laser at (0.05, 0.05) looking along +x, range 1.0 m: endpoint (1.05, 0.05). With 0.1 m
    # cells and the origin snapped to (0, 0): cells (0, 0..9) are crossed, (0, 10) is hit.
    g = beam_grid([[1.0]], [0.0], [[0.05, 0.05, 0.0]])
    np.testing.assert_allclose(g.origin_xy, [0.0, 0.0], atol=1e-12)
    assert g.shape == (1, 11)
    np.testing.assert_allclose(g.log_odds[0], [L_FREE] * 10 + [L_OCC], rtol=1e-6)
    assert g.misses.tolist() == [[1] * 10 + [0]]
    assert g.hits.tolist() == [[0] * 10 + [1]]
    assert g.ternary().tolist() == [[-1] * 10 + [100]]  # one miss (p 0.40) is not yet free


def test_each_cell_updated_once_per_scan_and_hits_take_precedence() -> None:
    # Two beams along +x in one scan, 1.0 m and 2.0 m: the long beam passes through the
    # short beam's endpoint cell (10), which stays a pure hit for this scan; cells 0..9 are
    # crossed by both beams but count one miss per scan.
    ranges = np.array([[1.0, 2.0]])
    g1 = beam_grid(ranges, [0.0, 0.0], [[0.05, 0.05, 0.0]])
    assert g1.misses[0].tolist() == [1] * 10 + [0] + [1] * 9 + [0]
    assert g1.hits[0].tolist() == [0] * 10 + [1] + [0] * 9 + [1]
    np.testing.assert_allclose(g1.log_odds[0, 10], L_OCC, rtol=1e-6)
    # The same scan twice: two updates per cell, summed in log-odds (Thrun Table 9.1).
    g2 = beam_grid(np.repeat(ranges, 2, 0), [0.0, 0.0], [[0.05, 0.05, 0.0]] * 2)
    np.testing.assert_allclose(g2.log_odds[0, :10], 2 * L_FREE, rtol=1e-6)
    np.testing.assert_allclose(g2.log_odds[0, [10, 20]], 2 * L_OCC, rtol=1e-6)


def test_log_odds_are_clamped() -> None:
    # 10 identical scans: 10 * 0.85 = 8.5 > l_max and 10 * -0.4 = -4 < l_min.
    g = beam_grid(np.full((10, 1), 1.0), [0.0], [[0.05, 0.05, 0.0]] * 10)
    np.testing.assert_allclose(g.log_odds[0, :10], L_MIN, rtol=1e-6)
    np.testing.assert_allclose(g.log_odds[0, 10], L_MAX, rtol=1e-6)
    assert g.hits[0, 10] == 10 and np.all(g.misses[0, :10] == 10)
    assert g.ternary()[0].tolist() == [0] * 10 + [100]


def test_no_return_beams_clear_only_when_configured() -> None:
    pose = [[0.05, 0.05, 0.0]]
    # r == sensor range_max (20 m): a no-return beam. Default: nothing is drawn.
    g = beam_grid([[20.0]], [0.0], pose)
    assert g.shape == (1, 1) and g.misses.sum() == 0 and g.hits.sum() == 0
    # Cleared to 1.0 m: laser at x 0.05 -> end 1.05, cells 0..10 free, no hit.
    g = beam_grid([[20.0]], [0.0], pose, no_return_clear_m=1.0)
    assert g.misses[0].tolist() == [1] * 11 and g.hits.sum() == 0
    # A 5 m return beyond the config's range_max_m (3 m) is a no-return beam too, cleared to
    # min(no_return_clear_m, r) = 1.0 m.
    g = beam_grid([[5.0]], [0.0], pose, range_max_m=3.0, no_return_clear_m=1.0)
    assert g.misses[0].tolist() == [1] * 11 and g.hits.sum() == 0
    g = beam_grid([[5.0]], [0.0], pose, range_max_m=3.0)
    assert g.hits.sum() == 0 and g.misses.sum() == 0
    # NaN and r <= range_min are ignored entirely.
    g = beam_grid([[np.nan, 0.0]], [0.0, 0.5], pose, no_return_clear_m=1.0)
    assert g.hits.sum() == 0 and g.misses.sum() == 0


def test_pose_and_laser_offset_place_the_endpoint() -> None:
    # Robot at (1.02, 2.03) facing +y, laser 0.2 m ahead: laser at (1.02, 2.23); a 1 m beam
    # at bearing 0 ends at (1.02, 3.23) (hand-computed).
    scan = LaserScan(
        stamp_s=0.0,
        ranges_m=np.array([1.0]),
        angles_rad=np.array([0.0]),
        range_min_m=0.0,
        range_max_m=20.0,
        odom_pose=None,
        laser_offset=np.array([0.2, 0.0, 0.0]),
    )
    pose = np.array([[1.02, 2.03, math.pi / 2]])
    g = render([scan], pose, GridConfig(resolution_m=0.1, margin_m=0.5))
    hit_cells = np.argwhere(g.hits > 0)
    assert hit_cells.tolist() == [g.world_to_cell([1.02, 3.23]).tolist()]
    crossed = g.cell_to_world(np.argwhere(g.misses > 0))
    np.testing.assert_allclose(crossed[:, 0], 1.05, atol=1e-9)  # the column x in [1.0, 1.1)
    np.testing.assert_allclose(np.sort(crossed[:, 1]), np.arange(2.25, 3.2, 0.1), atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(
    st.floats(0.0, 6.0),
    st.floats(0.0, 6.0),
    st.floats(-math.pi, math.pi),
    st.floats(0.05, 4.0),
)
def test_traversal_is_the_exact_cell_path(x0: float, y0: float, bearing: float, r: float) -> None:
    # Truth: the cells a densely sampled segment (step 1e-3 cell) passes through. The
    # traversal must contain them all and be a 4-connected path of exactly
    # |d col| + |d row| + 1 cells: the cells a segment crosses (Amanatides & Woo 1987).
    # A segment that runs along a cell boundary has no defined cell set (which side it is on
    # is floating-point rounding): leave those out.
    for start, direction in ((x0, math.cos(bearing)), (y0, math.sin(bearing))):
        on_line = abs(start / 0.1 - round(start / 0.1)) < 1e-6
        assume(not (on_line and abs(direction) < 1e-6))
    g = render_ranges([[r]], [bearing], [[x0, y0, 0.0]], GridConfig(resolution_m=0.1, margin_m=0.1))
    path = {tuple(c) for c in np.argwhere((g.misses > 0) | (g.hits > 0)).tolist()}
    end = np.array([x0 + r * math.cos(bearing), y0 + r * math.sin(bearing)])
    start_rc, end_rc = g.world_to_cell(np.array([[x0, y0], end]))
    t = np.linspace(0.0, 1.0, math.ceil(r / 0.1 * 1000) + 2)
    samples = np.array([x0, y0]) + t[:, None] * (end - [x0, y0])
    sampled = {tuple(c) for c in g.world_to_cell(samples).tolist()}
    assert sampled <= path
    assert len(path) == abs(int(end_rc[0] - start_rc[0])) + abs(int(end_rc[1] - start_rc[1])) + 1
    assert np.argwhere(g.hits > 0).tolist() == [end_rc.tolist()]
    cells = np.array(sorted(path))
    mask = np.zeros(g.shape, dtype=bool)
    mask[cells[:, 0], cells[:, 1]] = True
    assert ndimage.label(mask)[1] == 1  # one 4-connected component (label's default)


def test_world_cell_conventions() -> None:
    g = OccupancyGrid(np.zeros((20, 30), np.float32), 0.05, np.array([-1.0, 2.0]))
    # Row 0 is the lowest y; cell (0, 0)'s lower-left corner is the origin.
    assert g.world_to_cell([-1.0 + 0.025, 2.0 + 0.025]).tolist() == [0, 0]
    assert g.world_to_cell([-1.0 + 3.2 * 0.05, 2.0 + 7.9 * 0.05]).tolist() == [7, 3]
    rc = np.array([[0, 0], [19, 29], [5, 7]])
    np.testing.assert_allclose(g.cell_to_world(rc)[0], [-0.975, 2.025])
    assert (g.world_to_cell(g.cell_to_world(rc)) == rc).all()
    assert g.extent_xy == pytest.approx((-1.0, 0.5, 2.0, 3.0))
    assert g.contains(np.array([[0, 0], [20, 0], [0, -1]])).tolist() == [True, False, False]


def test_probabilities_ternary_binary_thresholds() -> None:
    # p = 1 / (1 + exp(-l)): l = 0 -> 0.5 (unknown); logit(0.196) = -1.4127; logit(0.65) = 0.619.
    lo = np.array([[0.0, -1.40, -1.42, 0.61, 0.63, L_MAX]], np.float32)
    g = OccupancyGrid(lo, 0.05, np.zeros(2))
    np.testing.assert_allclose(g.probabilities()[0, 0], 0.5)
    assert g.ternary().tolist() == [[-1, -1, 0, -1, 100, 100]]
    assert g.binary().tolist() == [[False, False, False, False, True, True]]
    assert g.ternary().dtype == np.int8


# ---------------------------------------------------------------------------------------------
# simulated office world (acceptance)
# ---------------------------------------------------------------------------------------------


def test_simulated_office_matches_the_wall_map(office_run) -> None:
    # Truth: the simulator's wall segments, rasterized into the same 5 cm grid; the wall cells
    # that the noise-free rays hit from the true poses (recall is over those).
    g = render(office_run.scans, office_run.true_poses, GridConfig(resolution_m=0.05))
    precision, recall, free_fraction = occupancy_scores(
        g, office_run.world.walls, office_run.scans, office_run.true_poses
    )
    assert precision >= 0.9, precision  # measured 1.000
    assert recall >= 0.9, recall  # measured 0.999
    assert free_fraction >= 0.9, free_fraction  # measured 0.961
    # Control: the same scores notice a map drawn from poses 0.2 m (4 cells) off.
    shifted = office_run.true_poses + np.array([0.2, 0.0, 0.0])
    g_bad = render(office_run.scans, shifted, GridConfig(resolution_m=0.05))
    assert occupancy_scores(g_bad, office_run.world.walls, office_run.scans, shifted)[0] < 0.7


def test_binary_mode_follows_its_rule_and_matches_the_walls(office_run) -> None:
    cfg = GridConfig(mode="binary")
    g = render(office_run.scans, office_run.true_poses, cfg)
    # The rule (GridConfig.mode): occupied iff hits >= 1 and hits >= misses; free iff
    # misses > hits; unknown where no ray reached.
    occupied = (g.hits > 0) & (g.hits >= g.misses)
    free = g.misses > g.hits
    t = g.ternary()
    assert np.array_equal(t == 100, occupied)
    assert np.array_equal(t == 0, free)
    assert np.array_equal(t == -1, (g.hits == 0) & (g.misses == 0))
    precision, recall, free_fraction = occupancy_scores(
        g, office_run.world.walls, office_run.scans, office_run.true_poses
    )
    assert precision >= 0.9 and recall >= 0.9 and free_fraction >= 0.9, (
        precision,
        recall,
        free_fraction,
    )


def test_render_scans_and_render_ranges_agree(office_run) -> None:
    scans = office_run.scans[:50]
    poses = office_run.true_poses[:50]
    g1 = render(scans, poses)
    g2 = render_ranges(
        np.stack([s.ranges_m for s in scans]),
        scans[0].angles_rad,
        poses,
        range_min_m=scans[0].range_min_m,
        range_max_m=scans[0].range_max_m,
        laser_offset=scans[0].laser_offset,
    )
    assert np.array_equal(g1.log_odds, g2.log_odds)
    np.testing.assert_allclose(g1.origin_xy, g2.origin_xy)


def test_the_map_is_identical_with_any_number_of_threads(
    office_run, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Each thread traces every beam through its own band of tile rows (GridConfig.threads),
    # so each cell is updated by one thread, in scan order: the same bits as one thread,
    # clamping and the once-per-scan rule included, in one pass and chunk by chunk.
    scans, poses = office_run.scans, office_run.true_poses
    store = ScanStore(scans)
    bands: list[list[tuple[int, int]]] = []  # the bands of every traced chunk
    row_bands = grid_module._row_bands

    def recorded(*args):  # type: ignore[no-untyped-def]
        bands.append(row_bands(*args))
        return bands[-1]

    monkeypatch.setattr(grid_module, "_row_bands", recorded)
    for cfg in (GridConfig(), GridConfig(mode="binary", no_return_clear_m=3.0)):
        one = render_tiled(scans, poses, cfg.model_copy(update={"threads": 1}))
        for threads in (2, 3, 7):
            many = cfg.model_copy(update={"threads": threads})
            for g in (
                render_tiled(scans, poses, many),
                render_tiled_chunks(poses, store.beam_chunk, many, chunk_scans=100),
            ):
                np.testing.assert_array_equal(g.tile_index, one.tile_index)
                np.testing.assert_array_equal(g.log_odds, one.log_odds)
                np.testing.assert_array_equal(g.hits, one.hits)
                np.testing.assert_array_equal(g.misses, one.misses)
    assert max(len(b) for b in bands) >= 3  # three threads or more, each on its own band


# ---------------------------------------------------------------------------------------------
# export
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def room():
    """A 6.04 m x 4.02 m room (walls at x = +-3.02, y = +-2.01, off the cell boundaries) seen
    by a robot turning on the spot at the origin, plus its grid at 5 cm."""
    world = World("room", np.array(rectangle(-3.02, -2.01, 3.02, 2.01)))
    # 37 poses on a 0.3 m circle, heading steps of 360/37 deg: the 1 deg beams fall between
    # one another's, so every wall cell gets hit.
    phi = np.linspace(0, 2 * np.pi, 37, endpoint=False)
    poses = np.stack([0.3 * np.cos(phi), 0.3 * np.sin(phi), phi], 1)
    run = simulate(world, trajectory=poses, seed=1)
    return run, render(run.scans, run.true_poses)


def test_map_server_georeferencing(room, tmp_path) -> None:
    _, g = room
    pgm_path, yaml_path = write_map_server(g, tmp_path / "room")
    assert pgm_path.read_bytes()[:2] == b"P5"
    meta = yaml.safe_load(yaml_path.read_text())
    assert meta["image"] == "room.pgm" and meta["negate"] == 0
    assert meta["occupied_thresh"] == 0.65 and meta["free_thresh"] == 0.196
    img = np.asarray(Image.open(tmp_path / meta["image"]))
    h = img.shape[0]
    res = meta["resolution"]
    ox, oy, _ = meta["origin"]

    def pixel(x: float, y: float) -> int:
        # map_server: origin = lower-left pixel corner, rows top-down.
        return int(img[h - 1 - math.floor((y - oy) / res), math.floor((x - ox) / res)])

    for y in np.linspace(-1.8, 1.8, 10):  # the east and west walls, known x
        assert pixel(3.02, y) == 0 and pixel(-3.02, y) == 0
    for x in np.linspace(-2.8, 2.8, 10):  # the north and south walls
        assert pixel(x, 2.01) == 0 and pixel(x, -2.01) == 0
    assert pixel(0.7, 0.4) == 254 and pixel(-2.0, -1.5) == 254  # inside the room: free
    assert pixel(3.5, 0.0) == 205 and pixel(0.0, -2.5) == 205  # behind the walls: unknown
    # The whole image is the ternary map flipped top-down.
    expected = np.select([g.ternary() == 100, g.ternary() == 0], [0, 254], 205)[::-1]
    assert np.array_equal(img, expected)


def test_png_has_the_map_and_the_trajectory(room, tmp_path) -> None:
    _, g = room
    traj = np.array([[0.0, 0.0], [1.5, 0.5], [2.0, -1.0]])
    out = write_png(g, tmp_path / "room.png", traj)
    with Image.open(out) as png:
        assert png.mode == "P"  # one byte a pixel: the map leaves grey levels free
        img = np.asarray(png.convert("RGB"))
    h, w = g.shape
    assert img.shape == (h, w, 3)
    c, r = g.world_to_cell([1.0, 1.0 / 3.0])[::-1]  # on the first leg of the trajectory
    assert tuple(img[h - 1 - r, c]) == (220, 30, 30)
    c, r = g.world_to_cell([0.0, 0.0])[::-1]
    assert tuple(img[h - 1 - r, c]) == (0, 160, 0)  # the start
    c, r = g.world_to_cell([3.02, 1.0])[::-1]
    assert img[h - 1 - r, c, 0] < 20  # a wall: p > 0.93 -> grey < 18
    c, r = g.world_to_cell([-1.0, -1.0])[::-1]
    assert img[h - 1 - r, c, 0] > 220  # free: p < 0.12 -> grey > 224


def test_png_of_a_map_of_every_grey_level_is_rgb_with_the_same_colours(tmp_path) -> None:
    # A map whose cells take every grey level 255 * (1 - p) leaves no palette entry for the
    # trajectory's colours: the PNG is RGB, each cell its own grey, the trajectory red.
    level = np.arange(256, dtype=np.float64)
    p = 1.0 - np.clip(level, 0.1, 254.9) / 255.0  # grey levels 0.1, 1, 2, ..., 254, 254.9
    row = np.log(p / (1.0 - p)).astype(np.float32)
    g = OccupancyGrid(np.tile(row, (4, 1)), resolution_m=0.1, origin_xy=np.zeros(2))
    out = write_png(g, tmp_path / "levels.png", np.array([[0.05, 0.05], [25.0, 0.05]]))
    with Image.open(out) as png:
        assert png.mode == "RGB"
        img = np.asarray(png)
    # rows top-down: the trajectory (y = 0.05 m) on the last, its start dot at the left
    assert np.array_equal(img[0, 8:, 0], level[8:].astype(np.uint8))
    assert np.array_equal(img[0, 8:, 0], img[0, 8:, 2])  # grey
    assert tuple(img[3, 128]) == (220, 30, 30)
    assert tuple(img[1, 0]) == (0, 160, 0)


def test_npz_round_trip(room, tmp_path) -> None:
    _, g = room
    with np.load(write_npz(g, tmp_path / "room.npz")) as z:
        assert np.array_equal(z["log_odds"], g.log_odds)
        assert np.array_equal(z["hits"], g.hits) and np.array_equal(z["misses"], g.misses)
        assert float(z["resolution_m"]) == g.resolution_m
        np.testing.assert_array_equal(z["origin_xy"], g.origin_xy)
    assert not list(tmp_path.glob(".*tmp"))  # no temporary file left behind


def test_plot_grid_draws_in_metric_coordinates(room, tmp_path) -> None:
    _, g = room
    fig = Figure()
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    traj = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    image, line = plot.grid(ax, g, traj)
    assert isinstance(image, AxesImage) and isinstance(line, Line2D)
    assert image.get_extent() == pytest.approx(list(g.extent_xy))
    np.testing.assert_array_equal(image.get_array(), g.probabilities())
    np.testing.assert_array_equal(line.get_xydata(), traj[:, :2])
    assert len(plot.grid(ax, g)) == 1
    fig.savefig(tmp_path / "plot.png")


# ---------------------------------------------------------------------------------------------
# errors
# ---------------------------------------------------------------------------------------------


def test_inconsistent_inputs_raise_grid_error() -> None:
    with pytest.raises(GridError, match="2 poses for 1 scans"):
        render_ranges([[1.0]], [0.0], np.zeros((2, 3)))
    with pytest.raises(GridError, match="not finite"):
        render_ranges([[1.0]], [0.0], [[np.nan, 0.0, 0.0]])
    with pytest.raises(GridError, match="max_cells"):
        render_ranges([[100.0]], [0.0], [[0.0, 0.0, 0.0]], GridConfig(max_cells=1000))
    with pytest.raises(GridError, match="angles_rad"):
        render_ranges([[1.0, 2.0]], [0.0], [[0.0, 0.0, 0.0]])


def test_config_rejects_unusable_thresholds() -> None:
    with pytest.raises(ValidationError, match="free_thresh"):
        GridConfig(free_thresh=0.7)
    with pytest.raises(ValidationError, match="l_min"):
        GridConfig(l_min=-1.0)  # logit(0.196) = -1.41: no cell could ever be free
    with pytest.raises(ValidationError):
        GridConfig(resolution_m=0.0)
    with pytest.raises(ValidationError):
        GridConfig(unknown_key=1)  # type: ignore[call-arg]


# ---------------------------------------------------------------------------------------------
# real logs with corrected poses (acceptance)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "relative", ["aces/aces-corrected.log.gz", "mit-csail/csail.log"], ids=["aces", "csail"]
)
def test_corrected_real_logs_give_single_straight_walls(relative: str, tmp_path) -> None:
    # Truth: GMapping-corrected poses (ACES) and the course's corrected poses (CSAIL), in each
    # scan's odom_pose. Proxies for "single, straight walls", thresholds from geometry:
    # - local wall thickness: a single straight wall rasterizes into a band 1-2 cells wide,
    #   whose cells lie within 0-0.5 cell RMS of their local line (the simulated office, with
    #   walls on cell boundaries, measures 0.50); a doubled or smeared wall (copies >= 2 cells
    #   apart) measures >= 1 cell. The median must be below the midpoint 0.75 cell.
    # - isolated occupied cells (no occupied 8-neighbour) are speckle; at most 15 %.
    # Control: the same scans on poses perturbed by 5 cm / 1 deg (sigma) must fail the
    # thickness proxy, showing it detects smeared walls.
    scans = list(open_log(shared_file(relative)))
    poses = np.stack([s.odom_pose for s in scans])  # type: ignore[misc]
    g = render(scans, poses)
    name = relative.split("/")[0]
    write_png(g, tmp_path / f"{name}.png", poses)
    thickness = float(np.median(local_wall_thickness_cells(g)))
    isolated = isolated_fraction(g)
    assert thickness < 0.75, thickness  # measured: aces 0.58, csail 0.71
    assert isolated < 0.15, isolated  # measured: aces 0.11, csail 0.05
    rng = np.random.default_rng(0)
    noisy = poses + rng.normal(0.0, [0.05, 0.05, math.radians(1.0)], poses.shape)
    g_noisy = render(scans, noisy)
    write_png(g_noisy, tmp_path / f"{name}-perturbed.png", noisy)
    assert float(np.median(local_wall_thickness_cells(g_noisy))) > 0.9  # measured 0.99, 1.05
