"""Tests of the compact scan storage (:mod:`iceg.scan_store`): exact round trips and the
flattened beams the occupancy grid renders from."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from frontends import LaserScan
from frontends.simulate import office_world, simulate
from iceg import scan_store
from iceg.grid import GridConfig, render_tiled, render_tiled_beams, render_tiled_chunks
from iceg.scan_store import RANGE_ENCODINGS, ScanStore


def _same(a: LaserScan, b: LaserScan) -> bool:
    return (
        a.stamp_s == b.stamp_s
        and a.ranges_m.dtype == b.ranges_m.dtype == np.float64
        and np.array_equal(a.ranges_m.view(np.int64), b.ranges_m.view(np.int64))  # every bit
        and np.array_equal(a.angles_rad.view(np.int64), b.angles_rad.view(np.int64))
        and a.range_min_m == b.range_min_m
        and a.range_max_m == b.range_max_m
        and (
            (a.odom_pose is None and b.odom_pose is None)
            or (
                a.odom_pose is not None
                and b.odom_pose is not None
                and np.array_equal(a.odom_pose, b.odom_pose)
            )
        )
        and np.array_equal(a.laser_offset, b.laser_offset)
        and a.source == b.source
        and a.odom_break == b.odom_break
    )


_floats = st.floats(-1e6, 1e6, allow_nan=False)


@st.composite
def scan_lists(draw: st.DrawFn) -> list[LaserScan]:
    n = draw(st.integers(0, 40))
    fans = [np.linspace(-1.5, 1.5, 11), np.linspace(-2.0, 2.0, 7), np.array([0.1])]
    out = []
    stamp = 0.0
    for k in range(n):
        angles = fans[draw(st.integers(0, 2))]
        ranges = np.array(
            draw(
                st.lists(
                    st.one_of(
                        st.floats(0, 100),
                        st.just(float("nan")),
                        st.just(float("inf")),
                        st.just(-0.0),
                        # printed with two or three decimals (a CARMEN log), or float32 (a bag)
                        st.integers(0, 40000).map(lambda c: c / 100.0),
                        st.integers(-(2**31), 2**31 - 1).map(lambda m: m / 1000.0),
                        st.floats(0, 100, width=32),
                    ),
                    min_size=len(angles),
                    max_size=len(angles),
                )
            )
        )
        stamp += draw(st.floats(0, 10))
        odom = None if draw(st.booleans()) else np.array([draw(_floats) for _ in range(3)])
        source = draw(
            st.sampled_from([f"log.clf:{k + 1}", "<memory>", "a:b:007", f"x:{k}:", "bag:/scan#3"])
        )
        out.append(
            LaserScan(
                stamp_s=stamp,
                ranges_m=ranges,
                angles_rad=angles.copy(),
                range_min_m=draw(st.floats(0, 1)),
                range_max_m=draw(st.floats(1, 100)),
                odom_pose=odom,
                laser_offset=np.array([draw(_floats) for _ in range(3)]),
                source=source,
                odom_break=draw(st.booleans()),
            )
        )
    return out


@settings(max_examples=60, deadline=None)
@given(scan_lists())
def test_scans_round_trip_exactly(scans: list[LaserScan]) -> None:
    store = ScanStore(scans)
    assert len(store) == len(scans)
    assert all(_same(a, b) for a, b in zip(store, scans, strict=True))
    if scans:
        assert _same(store[-1], scans[-1])
        assert store.stamp_s(-1) == scans[-1].stamp_s
        assert [s.source for s in store[1:3]] == [s.source for s in scans[1:3]]
        assert store.sources() == [s.source for s in scans]
        counts, ranges, angles, rmin, rmax, offsets = store.beams()
        np.testing.assert_array_equal(counts, [s.ranges_m.shape[0] for s in scans])
        np.testing.assert_array_equal(ranges, np.concatenate([s.ranges_m for s in scans]))
        np.testing.assert_array_equal(angles, np.concatenate([s.angles_rad for s in scans]))
        np.testing.assert_array_equal(rmin, np.repeat([s.range_min_m for s in scans], counts))
        np.testing.assert_array_equal(rmax, np.repeat([s.range_max_m for s in scans], counts))
        np.testing.assert_array_equal(offsets, np.stack([s.laser_offset for s in scans]))


def _contents(
    store: ScanStore,
) -> tuple[dict[str, np.ndarray], list[bytes], list[bytes], list[str]]:
    """Everything a store holds: its header rows, each scan's encoded ranges (bytes), its
    bearing and source tables."""
    n = len(store)
    head = {k: v[:n] for k, v in store._head.items()}
    data = [store._stored(k).tobytes() for k in range(n)]
    return head, data, list(store._angle_bits), list(store._source_table)


@settings(max_examples=40, deadline=None)
@given(scan_lists())
def test_a_scan_read_from_a_store_is_stored_again_without_encoding(
    scans: list[LaserScan],
) -> None:
    """A run's store takes its scans from the store the log was read into: it takes their
    encoding from there (no ``_encode``) and holds exactly what encoding them gives."""
    source = ScanStore(scans)
    encoded = ScanStore(scans)  # by _encode, scan by scan
    calls = []
    real = scan_store._encode
    try:
        scan_store._encode = lambda r: calls.append(1) or real(r)  # type: ignore[assignment]
        copied = ScanStore(source)
    finally:
        scan_store._encode = real
    assert not calls
    want, got = _contents(encoded), _contents(copied)
    assert want[0].keys() == got[0].keys()
    for k in want[0]:
        assert want[0][k].tobytes() == got[0][k].tobytes(), k
    assert want[1:] == got[1:]
    assert all(_same(a, b) for a, b in zip(copied, scans, strict=True))


def test_a_scan_changed_after_it_was_read_is_encoded_again() -> None:
    """Ranges written in place after a scan left its store are the ones stored."""
    source = ScanStore([_ranges_scan(np.array([1.25, 2.5, 7.75]))])
    scan = source[0]
    scan.ranges_m[1] = 2.004  # millimetres now: int32, not int16
    copy = ScanStore([scan])
    assert copy._head["encoding"][0] == 1
    np.testing.assert_array_equal(copy[0].ranges_m, [1.25, 2.004, 7.75])


def test_store_is_compact_and_renders_the_same_map() -> None:
    run = simulate(office_world(), seed=0)
    scans = run.scans[:150]
    store = ScanStore(scans)
    big = ScanStore(s for _ in range(20) for s in scans)  # 3000 scans
    per_scan = big.nbytes / len(big)
    beams = scans[0].ranges_m.shape[0]
    # The ranges (8 bytes a beam) and a small header; capacity at most doubles it.
    assert per_scan <= 2 * (8 * beams + 150)
    a = render_tiled(scans, run.true_poses[:150])
    counts, ranges, angles, rmin, rmax, offsets = store.beams()
    b = render_tiled_beams(run.true_poses[:150], offsets, counts, ranges, angles, rmin, rmax)
    np.testing.assert_array_equal(a.to_dense().log_odds, b.to_dense().log_odds)


def test_chunked_grid_equals_one_pass_and_chunks_slice_the_beams() -> None:
    """The grid rendered chunk by chunk (bounded memory) has the same cells, hits and
    misses as one pass over every beam, for any chunk size; chunks are slices of beams()."""
    run = simulate(office_world(), seed=1)
    scans = run.scans[:120]
    poses = run.true_poses[:120]
    store = ScanStore(scans)
    counts, ranges, angles, rmin, rmax, offsets = store.beams()
    starts = np.concatenate([[0], np.cumsum(counts)])
    for lo, hi in [(0, 120), (7, 8), (30, 71), (119, 120), (5, 5)]:
        c = store.beam_chunk(lo, hi)
        np.testing.assert_array_equal(c.ranges_m, ranges[starts[lo] : starts[hi]])
        np.testing.assert_array_equal(c.angles_rad, angles[starts[lo] : starts[hi]])
        np.testing.assert_array_equal(c.range_max_m, rmax[starts[lo] : starts[hi]])
        np.testing.assert_array_equal(c.laser_offsets, offsets[lo:hi])
    for cfg in (GridConfig(), GridConfig(mode="binary", no_return_clear_m=3.0)):
        one = render_tiled_beams(poses, offsets, counts, ranges, angles, rmin, rmax, cfg)
        for size in (1, 17, 50, 1000):
            chunked = render_tiled_chunks(poses, store.beam_chunk, cfg, chunk_scans=size)
            assert chunked.shape == one.shape
            np.testing.assert_array_equal(chunked.origin_xy, one.origin_xy)
            np.testing.assert_array_equal(chunked.tile_index, one.tile_index)
            np.testing.assert_array_equal(chunked.log_odds, one.log_odds)
            np.testing.assert_array_equal(chunked.hits, one.hits)
            np.testing.assert_array_equal(chunked.misses, one.misses)


def test_odometry_arrays() -> None:
    def scan(t: float, pose: list[float] | None, odom_break: bool = False) -> LaserScan:
        odom = None if pose is None else np.array(pose)
        return LaserScan(t, np.ones(2), np.array([0.0, 0.1]), 0.1, 5.0, odom, odom_break=odom_break)

    store = ScanStore(
        [scan(0.5, [1.0, 2.0, 0.3]), scan(0.7, None), scan(0.9, [4.0, 5.0, -1.0], True)]
    )
    stamps, odom, breaks = store.odometry
    assert stamps.tolist() == [0.5, 0.7, 0.9]
    np.testing.assert_array_equal(odom, [[1.0, 2.0, 0.3], [np.nan] * 3, [4.0, 5.0, -1.0]])
    assert breaks.tolist() == [False, False, True]


def _ranges_scan(ranges: np.ndarray) -> LaserScan:
    angles = np.linspace(-1.0, 1.0, ranges.shape[0])
    return LaserScan(0.0, ranges, angles, 0.0, 500.0, None)


def _numpy_encoding(ranges: np.ndarray) -> int:
    """The index of the first of RANGE_ENCODINGS whose numpy round trip (scale, round, cast,
    decode) gives back every bit of ``ranges``."""
    bits = ranges.view(np.int64)
    with np.errstate(invalid="ignore", over="ignore"):
        for k, (dtype, scale) in enumerate(RANGE_ENCODINGS[:-1]):
            if np.issubdtype(dtype, np.integer):
                scaled = np.rint(ranges * scale)
                info = np.iinfo(dtype)
                if not np.all((scaled >= info.min) & (scaled <= info.max)):
                    continue
                decoded = scaled.astype(dtype).astype(np.float64) / scale
            else:
                decoded = ranges.astype(dtype).astype(np.float64)
            if np.array_equal(decoded.view(np.int64), bits):
                return k
    return len(RANGE_ENCODINGS) - 1


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.floats(allow_nan=True, allow_infinity=True),
            st.just(-0.0),
            st.integers(-40000, 40000).map(lambda c: c / 100.0),
            st.integers(-(2**31) - 5, 2**31 + 5).map(lambda m: m / 1000.0),
            st.floats(-1e6, 1e6, width=32),
        ),
        max_size=30,
    )
)
def test_the_encoding_is_numpys_round_trip(values: list[float]) -> None:
    # The store picks the first encoding whose plain round trip (scale, round, cast, decode)
    # gives back every bit, including at the integer limits, for -0.0, NaN, infinities and
    # huge values, and its encoded ranges decode to those bits.
    ranges = np.array(values, dtype=np.float64)
    k, encoded = scan_store._encode(ranges)
    assert k == _numpy_encoding(ranges)
    dtype, scale = RANGE_ENCODINGS[k]
    assert encoded.dtype == np.dtype(dtype)
    decoded = scan_store._decode(encoded, scale)
    assert np.array_equal(decoded.view(np.int64), ranges.view(np.int64))


def test_each_scan_takes_the_narrowest_exact_encoding() -> None:
    """Hand-picked ranges: two decimals fit int16 centimetres, three decimals (or beyond
    327.67 m) int32 millimetres, float32 values float32, the rest float64; each decodes to
    the same bits."""
    cases = {
        "int16": np.array([1.4, 81.91, 0.0, 327.67, 0.01]),
        "int32": np.array([1.405, 81.91, 327.68, 2e6]),
        "float32": np.array([np.float32(0.1), np.float32(3.3), np.inf, np.nan]),
        "float64": np.array([0.1 + 1e-12, 1.0]),
    }
    names = [np.dtype(d).name for d, _ in RANGE_ENCODINGS]
    for expected, ranges in cases.items():
        store = ScanStore([_ranges_scan(ranges)])
        assert names[int(store._head["encoding"][0])] == expected
        got = store[0].ranges_m
        assert np.array_equal(got.view(np.int64), ranges.view(np.int64))
    # -0.0 is not +0.0: it cannot be an integer count of centimetres
    store = ScanStore([_ranges_scan(np.array([-0.0, 1.0]))])
    assert names[int(store._head["encoding"][0])] == "float32"
    assert np.signbit(store[0].ranges_m[0])


def test_a_carmen_log_costs_two_bytes_a_beam_and_blocks_are_never_copied(monkeypatch) -> None:
    """Ranges printed with two decimals take 2 bytes a beam; a store over several blocks
    (and a scan larger than a block) gives back every scan and the same flattened beams."""
    monkeypatch.setattr(scan_store, "BLOCK_BYTES", 1000)
    rng = np.random.default_rng(0)
    scans = [_ranges_scan(np.round(rng.uniform(0.1, 80.0, 361), 2)) for _ in range(30)]
    scans.insert(7, _ranges_scan(rng.uniform(0.1, 80.0, 400)))  # float64, 3200 bytes
    scans.insert(9, _ranges_scan(rng.uniform(0.1, 80.0, 3).astype(np.float32).astype(float)))
    store = ScanStore(scans)
    assert len(store._blocks) > 10
    blocks = list(store._blocks)
    store.append(scans[0])
    assert all(a is b for a, b in zip(blocks, store._blocks, strict=False))  # none copied
    scans.append(scans[0])
    for a, b in zip(store, scans, strict=True):
        assert np.array_equal(a.ranges_m.view(np.int64), b.ranges_m.view(np.int64))
    flat = np.concatenate([s.ranges_m for s in scans])
    np.testing.assert_array_equal(store.beams()[1], flat)
    starts = np.concatenate([[0], np.cumsum([s.ranges_m.shape[0] for s in scans])])
    for lo, hi in [(0, 5), (6, 11), (8, 10), (30, 33), (3, 3)]:
        chunk = store.beam_chunk(lo, hi).ranges_m
        np.testing.assert_array_equal(chunk, flat[starts[lo] : starts[hi]])
    monkeypatch.setattr(scan_store, "BLOCK_BYTES", 1 << 22)
    carmen = ScanStore(_ranges_scan(s.ranges_m) for s in scans if s.ranges_m.shape[0] == 361)
    assert carmen._used == 2 * 361 * len(carmen)


def test_bearings_that_differ_only_in_the_sign_of_a_zero_come_back_with_their_bits() -> None:
    # equal values, other bits: each scan keeps its own bearings (np.array_equal would
    # hand the second scan the first one's +0.0)
    fan = np.array([-0.5, 0.0, 0.5])
    signed = np.array([-0.5, -0.0, 0.5])
    scans = [
        LaserScan(float(k), np.ones(3), a, 0.0, 10.0, None)
        for k, a in enumerate((fan, signed, fan))
    ]
    store = ScanStore(scans)
    for want, got in zip(scans, store, strict=True):
        assert _same(want, got)
    assert np.signbit(store[1].angles_rad[1]) and not np.signbit(store[2].angles_rad[1])
