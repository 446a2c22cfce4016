"""The ICE feature map: landmarks anchored to graph nodes, references for matching, and
time-validity pruning (paper §III-C3, last paragraph; docs/design.md "Feature map and
time-validity").

Each landmark (an ICE feature) is anchored to the node that first observed it and stored in
that node's frame, so the map follows every re-optimisation of the pose graph. Each node also
keeps its scan's line segments (node frame) for point-to-line refinement. Everything is held
in flat numpy arrays (one row per landmark / segment), not in lists of objects.

Time-validity: a landmark in a reference is **expected** in a new scan when its support points
(the feature point and points a little along its walls; for an Intersection the nearest ends
of its two segments) lie inside the scan's field of view and range, are not occluded (no beam
around their bearing is shorter than their distance minus a tolerance) and its walls are not
seen at grazing incidence. It is **matched** when the matcher paired it. A landmark expected
often but matched rarely, or expected and unmatched for longer than ``validity_s``, is pruned.
"""

from __future__ import annotations

import logging
import math
import weakref
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import ClassVar, NamedTuple, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from frontends.scan import LaserScan
from iceg.landmark_association import (
    associate_scan,
    is_ascending,
    lookup_sorted,
    reference_geometry,
    rows_of_nodes,
    rows_taking_part,
    sorted_union,
)
from iceg.landmark_frames import (
    FeatureRows,
    frame_inverse,
    keep_better,
    move_features,
    move_points,
    poses_in_frame,
)
from iceg.matching.geometry import PolarProfile, transform_line_rows
from iceg.matching.matcher import walls_seen_through
from iceg.table_rows import drop_rows_in_place
from iceg.types import FeatureKind, MatchResult, ScanFeatures
from iceg.visibility import (
    beam_profile,
    count_observations,
    expected_landmarks,
    pruned_landmarks,
    visibility_geometry,
)
from iceg_common.errors import FeatureMapError
from iceg_common.ids import sorted_unique
from iceg_common.se2 import compose

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

#: Pruning reasons recorded in :attr:`FeatureMap.pruned`.
PRUNED_RATIO, PRUNED_VALIDITY = 1, 2

NodePoses = Mapping[int, ArrayLike] | tuple[ArrayLike, ArrayLike]

CORNER = int(FeatureKind.CORNER)
EOW = int(FeatureKind.EOW)
INTERSECTION = int(FeatureKind.INTERSECTION)

#: Sensor range assumed for a reference before any scan was added, metres.
_DEFAULT_RANGE_MAX_M = 20.0
#: Beam spacing when too few beams to measure it, radians.
_FALLBACK_SPACING_RAD = math.radians(1.0)
#: Beam spacing of a profile whose bearings all coincide, radians.
_DEGENERATE_SPACING_RAD = 0.01
#: Fewest returns from which a profile measures its beam spacing.
_MIN_BEAMS_FOR_SPACING = 3
#: Bearing differences at or below this are the same bearing, radians.
_MIN_GAP_RAD = 1e-9
#: Two neighbouring returns farther apart than this many beam spacings leave a gap (missing
#: beams) in which nothing can be judged visible.
_MAX_GAP_BEAMS = 1.6
#: Floor of a vector norm before dividing by it, metres.
_MIN_NORM = 1e-9
#: No landmark ids (a bookkeeping without a reference).
_NO_IDS = np.zeros(0, dtype=np.int64)

#: How much a feature kind tells (a Corner has a position and two walls, an EOW a position
#: and one wall, an Intersection a virtual position): a landmark takes the kind of a matched
#: observation that ranks higher.
_RANK = np.zeros(3, dtype=np.int64)
_RANK[CORNER], _RANK[EOW], _RANK[INTERSECTION] = 2, 1, 0


class FeatureMapConfig(BaseModel):
    """Association, visibility and time-validity settings of the feature map (paper §III-C3:
    "each feature has a time-validity property ... features placed in visible area but
    observed rarely will be omitted from the map"; docs/design.md "Feature map and time-validity").
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    association_gate_m: float = Field(
        default=0.3,
        gt=0.0,
        description="A new feature the matcher did not pair is still associated with a "
        "reference landmark of a compatible kind within this distance (at the matched pose) "
        "instead of becoming a new landmark.",
    )
    expected_max_range_m: float = Field(
        default=7.0,
        gt=0.0,
        description="A landmark is expected only within this distance: farther features are "
        "extracted unreliably (paper eq. 3: precision falls with distance).",
    )
    fov_margin_deg: float = Field(
        default=2.0,
        ge=0.0,
        description="Margin inside the scan's angular limits for a support point to count as "
        "in the field of view (docs/design.md: expected = inside the current field of view).",
    )
    occlusion_tolerance_m: float = Field(
        default=0.2,
        gt=0.0,
        description="A support point is occluded when a beam around its bearing is shorter "
        "than its distance minus this (docs/design.md: the scan's range at its bearing is not "
        "shorter than its distance).",
    )
    support_offset_m: float = Field(
        default=0.3,
        gt=0.0,
        description="Distance along each wall of a Corner/EOW of its extra support points: a "
        "wall hidden behind another (a box corner with one face visible) is not expected.",
    )
    min_incidence_deg: float = Field(
        default=20.0,
        ge=0.0,
        lt=90.0,
        description="A Corner or EOW is not expected when one of its walls is seen at less "
        "than this angle (grazing: the extractor cannot find it).",
    )
    min_expected: int = Field(
        default=15,
        ge=1,
        description="Ratio pruning applies once a landmark was expected this many times "
        "(paper §III-C3: 'placed in visible area but observed rarely').",
    )
    min_match_ratio: float = Field(
        default=0.15,
        ge=0.0,
        le=1.0,
        description="Pruned when matched / expected falls below this after min_expected.",
    )
    validity_s: float = Field(
        default=10.0,
        gt=0.0,
        description="Pruned when expected but not matched for longer than this since its last "
        "match (seconds; paper §III-C3 'time-validity'), confirmed by min_misses expected "
        "misses over miss_confirm_s.",
    )
    miss_confirm_s: float = Field(
        default=3.0,
        ge=0.0,
        description="Validity pruning also needs the misses to have lasted this long (seconds "
        "since the first expected miss after the last match): a landmark not seen for a long "
        "while is not removed by one glance that misses it.",
    )
    min_misses: int = Field(
        default=3,
        ge=1,
        description="Validity pruning needs at least this many consecutive expected misses "
        "(one missed extraction does not remove a landmark).",
    )
    bookkeeping_recent_nodes: int | None = Field(
        default=200,
        ge=0,
        description="Landmarks a matched scan associates, merges and counts as expected: those "
        "of the reference it was matched against, plus those last matched (or created) by one "
        "of this many most recent nodes; None: every landmark with an anchor pose. Older "
        "landmarks are left alone because the estimate of a place revisited after a long "
        "loop can be off by metres before the loop closes: there they would be missed, merged "
        "or pruned wrongly, and the loop closure needs them.",
    )
    reference_points: bool = Field(
        default=False,
        description="Keep every node's scan points and put those of the chosen nodes into a "
        "reference: the matcher then also uses the off-segment points (PL-ICP rows; more "
        "accurate where walls leave the pose open, about 1 ms slower per match).",
    )
    replace_ratio: float = Field(
        default=0.5,
        gt=0.0,
        le=1.0,
        description="A matched observation replaces a landmark's stored position when its "
        "covariance trace is below this fraction of the stored one (keep the best view).",
    )


@dataclass(frozen=True, eq=False)
class LandmarkView:
    """Landmarks in a common frame (see :meth:`FeatureMap.world_landmarks`).

    Attributes:
        ids: ``(L,)`` int64 landmark ids.
        anchor: ``(L,)`` int64 anchor node ids.
        kind: ``(L,)`` int64 :class:`~iceg.types.FeatureKind`.
        xy: ``(L, 2)`` float64 positions, metres.
        cov: ``(L, 2, 2)`` float64 position covariances, m².
        directions: ``(L, 2, 2)`` float64 unit wall directions (NaN where none).
        opening_rad: ``(L,)`` float64 opening angles (NaN for EOW).
        n_expected: ``(L,)`` int64 times expected.
        n_matched: ``(L,)`` int64 times matched.
        last_matched_s: ``(L,)`` float64 stamp of the last match (creation stamp if never).
    """

    ids: IntArray
    anchor: IntArray
    kind: IntArray
    xy: FloatArray
    cov: FloatArray
    directions: FloatArray
    opening_rad: FloatArray
    n_expected: IntArray
    n_matched: IntArray
    last_matched_s: FloatArray

    def __len__(self) -> int:
        return int(self.ids.shape[0])


@dataclass(frozen=True, eq=False)
class MapUpdate:
    """What one :meth:`FeatureMap.update` did.

    Attributes:
        node_id: The node updated.
        matched_ids: ``(A,)`` int64 landmark ids matched (associated) by this scan.
        added_ids: ``(N,)`` int64 ids of new landmarks.
        expected_ids: ``(E,)`` int64 ids of landmarks expected in this scan.
        pruned_ids: ``(R,)`` int64 ids pruned after this scan.
        merged_ids: ``(D,)`` int64 ids of duplicate landmarks merged into a matched one
            (the same physical feature anchored to another node).
    """

    node_id: int
    matched_ids: IntArray
    added_ids: IntArray
    expected_ids: IntArray
    pruned_ids: IntArray
    merged_ids: IntArray


@dataclass(frozen=True, eq=False)
class PrunedLandmarks:
    """Record of pruned landmarks (anchor frame), for analysis and tests.

    Attributes:
        ids, anchor, kind: ``(R,)`` int64.
        xy: ``(R, 2)`` float64 position in the anchor's frame, metres.
        stamp_s: ``(R,)`` float64 time of pruning.
        created_s: ``(R,)`` float64 time of creation.
        last_matched_s: ``(R,)`` float64 time of the last match.
        reason: ``(R,)`` int64 ``PRUNED_RATIO`` or ``PRUNED_VALIDITY``.
    """

    ids: IntArray
    anchor: IntArray
    kind: IntArray
    xy: FloatArray
    stamp_s: FloatArray
    created_s: FloatArray
    last_matched_s: FloatArray
    reason: IntArray


@dataclass(frozen=True, eq=False)
class MapCheckpoint:
    """A :class:`FeatureMap`'s state before one or more updates, for
    :meth:`FeatureMap.restore` (:meth:`FeatureMap.checkpoint`). The landmark table is
    copied; the segments, points, touched landmarks, node blocks and pruning records only
    grow in an update, so their sizes are enough.
    """

    landmarks: _Landmarks
    map_token: object  # the map it was taken from
    n_rows: tuple[int, int, int]  # segments, points, touched landmarks
    n_blocks: tuple[int, int, int]  # node blocks of each (dicts, in insertion order)
    n_pruned: int
    scalars: tuple[int, int, float, float]  # next id, merged, range max (m), last stamp (s)


@dataclass(frozen=True, eq=False)
class MapReference:
    """A matching reference built by :meth:`FeatureMap.reference`, with the snapshot of node
    poses it was built from (what :meth:`FeatureMap.update` needs after a match against it).

    Attributes:
        features: The reference as :class:`~iceg.types.ScanFeatures` in the frame of
            ``frame_pose`` (give this to the matcher); ``ids`` are landmark ids.
        frame_pose: ``(3,)`` float64 map-frame pose of the reference frame,
            ``[x_m, y_m, theta_rad]``.
        node_ids: ``(N,)`` int64 ascending ids of the node-pose snapshot.
        node_poses: ``(N, 3)`` float64 map-frame poses of those nodes.
        map_token: Identity of the map that built it (a reference is only valid there).
    """

    features: ScanFeatures
    frame_pose: FloatArray
    node_ids: IntArray
    node_poses: FloatArray
    map_token: object = field(repr=False)

    @property
    def landmark_ids(self) -> IntArray:
        """``(K,)`` int64 landmark id of each reference feature."""
        return self.features.ids

    def without_walls_seen_through(
        self, points_xy: FloatArray, tolerance_m: float, profile: PolarProfile | None = None
    ) -> MapReference:
        """This reference without the walls that a scan taken at its frame sees through more
        than it confirms (``iceg.matching.matcher.walls_seen_through``): a door that opened,
        a person who walked on. The wall is gone, and a new scan that sees past it would
        otherwise fail the matcher's free-space check at its true pose (on the ACES log, 23 of
        44 failed keyframes). Walls the scan does not see (outside its field of view, behind
        other walls, at grazing incidence) are kept. Landmarks and points are unchanged.

        Args:
            points_xy: ``(P, 2)`` float64 scan points (metres) seen from the origin of the
                reference frame: the scan of the node at ``frame_pose``, whose pose the
                reference's walls are placed against.
            tolerance_m: A beam sees through a wall when it reaches this far beyond it.
            profile: ``PolarProfile.from_points(points_xy, r)`` if the caller has it (the
                scan's matching profile, ``iceg.matching.matcher.scan_derived``); used when
                ``r`` is this reference's ``range_max_m``, else computed here.

        Returns:
            The reference without those walls (``self`` when none is dropped).
        """
        f = self.features
        if f.seg_endpoints.shape[0] == 0 or points_xy.shape[0] < 3:
            return self
        if profile is None or profile.range_max_m != float(f.range_max_m):
            profile = PolarProfile.from_points(points_xy, float(f.range_max_m))
        see, confirmed = walls_seen_through(f.seg_endpoints, profile, tolerance_m)
        keep = see <= confirmed
        if keep.all():
            return self
        walls = replace(
            f,
            seg_endpoints=f.seg_endpoints[keep],
            seg_lines=f.seg_lines[keep],
            seg_cov=f.seg_cov[keep],
            seg_point_range=f.seg_point_range[keep],
        )
        return replace(self, features=walls)


_C = TypeVar("_C", bound="_Columns")

#: Initial row capacity of a growing column container (:class:`_Columns`).
_MIN_CAPACITY = 64
#: From this many landmarks on, a reference finds its landmarks through the ids its nodes
#: touched (:class:`_Touched`) instead of a pass over every landmark. The pass streams
#: through the table, the index reads it at random: on MIT CSAIL (about 1500 landmarks) the
#: pass cost 31 µs a call and the index 52; the index stays near 40 µs at any size, the
#: pass grew to 88 µs at 3000 and 549 µs at 30000 (docs/design.md, "Landmarks by node").
#: The compiled pass (:func:`~iceg.landmark_association.rows_of_nodes`) costs 13 / 26 / 249
#: µs at 1500 / 3000 / 30000 for scattered nodes and 2 / 4 / 27 µs for a run of ids (a
#: local map), so the index still pays from a few thousand landmarks on.
_TOUCHED_FROM_LANDMARKS = 4096


@dataclass
class _Columns:
    """Rows held as one numpy array per field (first axis: row); subclasses are dataclasses
    whose ``SPEC`` gives each field's dtype and trailing shape.

    Each field is a view of the first rows of a buffer with spare capacity that doubles when
    full, so appending rows costs amortized O(rows appended), not O(rows held).
    """

    SPEC: ClassVar[dict[str, tuple[type, tuple[int, ...]]]] = {}

    def __post_init__(self) -> None:
        self._bufs: dict[str, np.ndarray] = {name: getattr(self, name) for name in self.SPEC}
        self._cap = len(self)
        self._owned = False  # the buffers are the constructor's arrays (never written)
        # The buffers as words for drop() (None: build them from the buffers first).
        self._words: tuple[tuple[np.ndarray, ...], IntArray] | None = None

    @classmethod
    def empty(cls: type[_C]) -> _C:
        """No rows."""
        return cls(**{k: np.zeros((0, *shape), dtype=dt) for k, (dt, shape) in cls.SPEC.items()})

    def __len__(self) -> int:
        return int(getattr(self, next(iter(self.SPEC))).shape[0])

    def append(self: _C, other: _C) -> None:
        """Append ``other``'s rows (cast to this container's dtypes)."""
        self.extend(len(other), **{name: getattr(other, name) for name in self.SPEC})

    def extend(self, m: int, **columns: ArrayLike) -> None:
        """Append ``m`` rows: each field's values, ``m`` rows of them or one value for every
        row (cast to the field's dtype, as ``astype`` does)."""
        n = len(self)
        if n + m > self._cap:
            cap = max(2 * self._cap, n + m, _MIN_CAPACITY)
            for name in self.SPEC:
                mine = getattr(self, name)
                buf = np.empty((cap, *mine.shape[1:]), dtype=mine.dtype)
                buf[:n] = mine
                self._bufs[name] = buf
            self._cap, self._owned = cap, True
            self._words = None
        for name in self.SPEC:
            buf = self._bufs[name]
            buf[n : n + m] = columns[name]
            setattr(self, name, buf[: n + m])

    def take(self: _C, rows: IntArray | BoolArray) -> _C:
        """A copy holding the selected rows (indices or a mask)."""
        return type(self)(**{name: getattr(self, name)[rows] for name in self.SPEC})

    def copy(self: _C) -> _C:
        """A copy of every row (its own arrays, no spare capacity)."""
        return type(self)(**{name: getattr(self, name).copy() for name in self.SPEC})

    def truncate(self, n: int) -> None:
        """Keep the first ``n`` rows (the rows beyond are the next appends' to overwrite)."""
        for name in self.SPEC:
            setattr(self, name, getattr(self, name)[:n])

    def drop(self, rows: IntArray) -> None:
        """Remove ``rows`` (indices), the others kept in order, in place: the kept rows move
        down within the container's buffers, so a drop allocates nothing (a fresh buffer of a
        large table costs a page fault per page) and keeps the spare capacity; every column
        in one compiled call (:func:`~iceg.table_rows.drop_rows_in_place`, which moves the
        8-byte values' bits).

        Column arrays read from the container before the drop are stale after it. Arrays
        given to the constructor are never written: the first drop copies them.
        """
        n = len(self)
        gone = sorted_unique(rows)
        kept = n - gone.shape[0]
        if not self._owned:
            self._bufs = {name: getattr(self, name).copy() for name in self.SPEC}
            self._cap, self._owned = n, True
            self._words = None
        if self._words is None:
            self._words = _row_words(self._bufs, self.SPEC)
        drop_rows_in_place(self._words[0], self._words[1], gone, n)
        for name in self.SPEC:
            setattr(self, name, self._bufs[name][:kept])


def _row_words(
    bufs: dict[str, np.ndarray], spec: dict[str, tuple[type, tuple[int, ...]]]
) -> tuple[tuple[np.ndarray, ...], IntArray]:
    """Every column buffer as flat int64 words (views) and the words per row of each, for
    :func:`~iceg.table_rows.drop_rows_in_place` (every field of a :class:`_Columns` holds
    8-byte values)."""
    words = tuple(bufs[name].reshape(-1).view(np.int64) for name in spec)
    per_row = np.array([math.prod(shape) for _, shape in spec.values()], dtype=np.int64)
    return words, per_row


@dataclass
class _Landmarks(_Columns):
    """Landmarks, one row each, geometry in the anchor node's frame (metres, radians)."""

    SPEC: ClassVar[dict[str, tuple[type, tuple[int, ...]]]] = {
        "id": (np.int64, ()),
        "anchor": (np.int64, ()),
        "kind": (np.int64, ()),
        "xy": (np.float64, (2,)),
        "cov": (np.float64, (2, 2)),
        "dirs": (np.float64, (2, 2)),
        "opening": (np.float64, ()),
        "support": (np.float64, (3, 2)),
        "wall_p": (np.float64, (2, 2)),
        "wall_d": (np.float64, (2, 2)),
        "wall_side": (np.float64, (2,)),
        "n_expected": (np.int64, ()),
        "n_matched": (np.int64, ()),
        "misses": (np.int64, ()),
        "created_s": (np.float64, ()),
        "last_matched_s": (np.float64, ()),
        "first_miss_s": (np.float64, ()),
        "last_node": (np.int64, ()),
    }

    id: IntArray  # (L,) landmark id
    anchor: IntArray  # (L,) anchor node
    kind: IntArray  # (L,) FeatureKind
    xy: FloatArray  # (L, 2) position
    cov: FloatArray  # (L, 2, 2) position covariance, m²
    dirs: FloatArray  # (L, 2, 2) unit wall directions (NaN where none)
    opening: FloatArray  # (L,) opening angle, rad
    support: FloatArray  # (L, 3, 2) visibility support points (see _geometry)
    wall_p: FloatArray  # (L, 2, 2) a point on each wall
    wall_d: FloatArray  # (L, 2, 2) each wall's direction
    wall_side: FloatArray  # (L, 2) side of each wall the sensor stood on (+1 / -1)
    n_expected: IntArray  # (L,) times expected
    n_matched: IntArray  # (L,) times matched
    misses: IntArray  # (L,) consecutive expected misses
    created_s: FloatArray  # (L,) creation stamp
    last_matched_s: FloatArray  # (L,) stamp of the last match (creation if never)
    first_miss_s: FloatArray  # (L,) first expected miss since the last match (NaN: none)
    last_node: IntArray  # (L,) node that last matched (or created) it

    def in_frame(self, rows: IntArray, frame_from_anchor: FloatArray) -> LandmarkView:
        """The landmarks ``rows`` ``(L,)`` in another frame, given each one's anchor pose
        ``(L, 3)`` there (copies of the rows: only the fields of the view are gathered)."""
        xy, cov, directions = move_features(rows, frame_from_anchor, self.xy, self.cov, self.dirs)
        return LandmarkView(
            ids=self.id[rows],
            anchor=self.anchor[rows],
            kind=self.kind[rows],
            xy=xy,
            cov=cov,
            directions=directions,
            opening_rad=self.opening[rows],
            n_expected=self.n_expected[rows],
            n_matched=self.n_matched[rows],
            last_matched_s=self.last_matched_s[rows],
        )


@dataclass
class _Segments(_Columns):
    """Every node's line segments, one row each, in the node's frame."""

    SPEC: ClassVar[dict[str, tuple[type, tuple[int, ...]]]] = {
        "node": (np.int64, ()),
        "ep": (np.float64, (2, 2)),
        "lines": (np.float64, (2,)),
        "cov": (np.float64, (2, 2)),
        "pr": (np.int64, (2,)),
    }

    node: IntArray  # (M,) node id
    ep: FloatArray  # (M, 2, 2) endpoints, metres
    lines: FloatArray  # (M, 2) Hessian (alpha_rad, rho_m)
    cov: FloatArray  # (M, 2, 2) covariance of (alpha, rho)
    pr: IntArray  # (M, 2) point range in the node's own points (-1: none kept)

    def in_frame(
        self, rows: IntArray, frame_from_node: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Endpoints ``(M, 2, 2)``, lines ``(M, 2)`` and their covariances ``(M, 2, 2)`` of
        the segments ``rows`` ``(M,)`` in another frame, given each one's node pose ``(M, 3)``
        there."""
        lines, cov = transform_line_rows(rows, frame_from_node, self.lines, self.cov)
        return move_points(frame_from_node, self.ep[rows], True), lines, cov


@dataclass
class _Points(_Columns):
    """Every node's scan points (kept with ``reference_points``), node frame, metres."""

    SPEC: ClassVar[dict[str, tuple[type, tuple[int, ...]]]] = {
        "node": (np.int64, ()),
        "xy": (np.float64, (2,)),
    }

    node: IntArray  # (P,)
    xy: FloatArray  # (P, 2)


@dataclass
class _Touched(_Columns):
    """Every node's landmarks: the ids it created or matched, one block of rows per node (a
    landmark's anchor and its last matching node both hold its id; a block may also hold
    ids since matched from a later node, or merged and pruned)."""

    SPEC: ClassVar[dict[str, tuple[type, tuple[int, ...]]]] = {"id": (np.int64, ())}

    id: IntArray  # (T,) landmark id


def compile_table_moves() -> None:
    """Drop the row of a one-row landmark table, so that the row moves' compiled kernel
    (:func:`~iceg.table_rows.drop_rows_in_place`) loads, or compiles on a new numba cache,
    before a run's first merge or pruning needs it (:mod:`iceg.kernel_warmup`)."""
    table = _Landmarks.empty()
    table.extend(1, **dict.fromkeys(_Landmarks.SPEC, 0))
    table.drop(np.zeros(1, dtype=np.int64))


#: Dtype and trailing shape of each :class:`PrunedLandmarks` field.
_PRUNED_SPEC: dict[str, tuple[type, tuple[int, ...]]] = {
    "ids": (np.int64, ()),
    "anchor": (np.int64, ()),
    "kind": (np.int64, ()),
    "xy": (np.float64, (2,)),
    "stamp_s": (np.float64, ()),
    "created_s": (np.float64, ()),
    "last_matched_s": (np.float64, ()),
    "reason": (np.int64, ()),
}


def _state_array(
    state: Mapping[str, np.ndarray], key: str, dtype: type, shape: tuple[int, ...]
) -> np.ndarray:
    """``state[key]`` checked against a dtype and trailing shape (``from_state``)."""
    a = np.asarray(state[key])
    if a.dtype != np.dtype(dtype) or a.shape[1:] != shape:
        raise FeatureMapError(
            f"FeatureMap.from_state: {key} must be {np.dtype(dtype)} (n, *{shape}), got "
            f"{a.dtype} {a.shape}"
        )
    return np.array(a, copy=True)


@dataclass(frozen=True, eq=False)
class _BeamProfile:
    """A scan's ranges sorted by bearing: what the visibility test
    (:func:`iceg.visibility.expected_landmarks`) looks landmarks up in.

    Attributes:
        bearing: ``(B,)`` float64 ascending bearings, radians, sensor frame.
        range_m: ``(B,)`` float64 ranges, metres (0 for an invalid beam, inf beyond range).
        spacing_rad: Typical angular spacing of consecutive beams.
        sensor_pose: ``(3,)`` laser pose in the robot frame, or ``None`` when the bearings
            are seen from the robot frame's origin.
    """

    bearing: FloatArray
    range_m: FloatArray
    spacing_rad: float
    sensor_pose: FloatArray | None

    @classmethod
    def of_scan(cls, scan: LaserScan) -> _BeamProfile:
        """Every beam of ``scan``: invalid returns block the view, max-range ones do not
        (compiled, :func:`~iceg.visibility.beam_profile`)."""
        ang, beam_r, spacing = beam_profile(  # own copies: one compiled array type
            np.array(scan.angles_rad, dtype=np.float64),
            np.array(scan.ranges_m, dtype=np.float64),
            float(scan.range_min_m),
            float(scan.range_max_m),
        )
        spacing = float(spacing) if ang.shape[0] > 1 else _FALLBACK_SPACING_RAD
        return cls(ang, beam_r, spacing, np.asarray(scan.laser_offset, dtype=np.float64))

    @classmethod
    def of_points(cls, points_xy: FloatArray) -> _BeamProfile:
        """Points ``(P, 2)`` (metres) seen from the frame's origin."""
        pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
        b = np.arctan2(pts[:, 1], pts[:, 0])
        r = np.hypot(pts[:, 0], pts[:, 1])
        order = np.argsort(b, kind="stable")
        b, r = b[order], r[order]
        if b.shape[0] >= _MIN_BEAMS_FOR_SPACING:
            gaps = np.diff(b)
            real = gaps > _MIN_GAP_RAD
            spacing = float(np.median(gaps[real])) if np.any(real) else _DEGENERATE_SPACING_RAD
        else:
            spacing = _FALLBACK_SPACING_RAD
        return cls(b, r, spacing, None)


@dataclass(frozen=True, eq=False)
class _Near:
    """Landmarks taking part in one scan's bookkeeping, placed in the new node's frame."""

    rows: IntArray  # (n,) landmark rows
    anchor_in_new: FloatArray  # (n, 3) anchor poses in the new node's frame
    xy_new: FloatArray  # (n, 2) positions in the new node's frame
    slot: IntArray  # (L,) row -> index into rows, -1 when not taking part


@dataclass(frozen=True, eq=False)
class _Bookkeeping:
    matched_ids: IntArray
    expected_ids: IntArray
    new_mask: BoolArray  # (K,) new features that become landmarks
    merge_rows: IntArray  # rows of duplicates to merge


def _node_pose_table(node_poses: NodePoses) -> tuple[IntArray, FloatArray]:
    if isinstance(node_poses, tuple):
        ids = np.asarray(node_poses[0], dtype=np.int64).reshape(-1)
        poses = np.asarray(node_poses[1], dtype=np.float64).reshape(-1, 3)
    else:
        ids = np.fromiter((int(k) for k in node_poses), dtype=np.int64, count=len(node_poses))
        poses = np.array([np.asarray(node_poses[k], dtype=np.float64) for k in node_poses])
        poses = poses.reshape(-1, 3)
    if ids.shape[0] != poses.shape[0]:
        raise FeatureMapError(
            f"node_poses: {ids.shape[0]} ids but {poses.shape[0]} poses; pass a dict "
            "{node_id: (3,) pose} or a tuple (ids (N,), poses (N, 3))"
        )
    if is_ascending(ids):  # sorted already (tables usually are)
        return ids.copy(), poses.copy()
    order = np.argsort(ids, kind="stable")
    return ids[order], poses[order]


def _node_blocks(node: IntArray) -> dict[int, tuple[int, int]]:
    """``{node: (start, stop)}`` of a node column made of one contiguous block per node."""
    if node.shape[0] == 0:
        return {}
    starts = np.flatnonzero(np.r_[True, node[1:] != node[:-1]])
    stops = np.r_[starts[1:], node.shape[0]]
    blocks = {int(node[a]): (int(a), int(b)) for a, b in zip(starts, stops, strict=True)}
    if len(blocks) != starts.shape[0]:
        raise FeatureMapError("FeatureMap.from_state: a node's rows are not contiguous")
    return blocks


def _block_rows(blocks: Mapping[int, tuple[int, int]], nodes: IntArray) -> IntArray:
    """Ascending rows of the blocks of ``nodes`` (nodes without a block have none)."""
    spans = sorted(blocks[n] for n in nodes.tolist() if n in blocks)
    if not spans:
        return np.zeros(0, dtype=np.int64)
    # Blocks are appended node by node: a run of nodes is mostly one run of rows.
    merged = [list(spans[0])]
    for a, b in spans[1:]:
        if a == merged[-1][1]:
            merged[-1][1] = b
        else:
            merged.append([a, b])
    if len(merged) == 1:
        return np.arange(merged[0][0], merged[0][1], dtype=np.int64)
    return np.concatenate([np.arange(a, b, dtype=np.int64) for a, b in merged])


#: ``(support, wall_p, wall_d, wall_side)`` of :func:`_geometry`.
_VisibilityGeometry = tuple[FloatArray, FloatArray, FloatArray, FloatArray]


def _geometry(features: ScanFeatures, offset_m: float) -> _VisibilityGeometry:
    """Visibility geometry of each feature in its scan's frame (NaN-padded; compiled,
    :func:`~iceg.visibility.visibility_geometry`).

    Returns:
        ``support`` ``(K, 3, 2)``: points that must be in view and not occluded: the point
        and ``offset_m`` along each wall for Corners/EOWs; for an Intersection a point
        ``offset_m`` inside each of its two segments from the end nearest to it.
        ``wall_p``, ``wall_d`` ``(K, 2, 2)``: a point on each wall and the wall's direction.
        ``wall_side`` ``(K, 2)``: on which side of each wall the sensor stood (+1 / -1): a
        wall is extracted from the side it was seen from.
    """
    return visibility_geometry(
        np.ascontiguousarray(features.kind, dtype=np.int64),
        np.ascontiguousarray(features.xy, dtype=np.float64).reshape(-1, 2),
        np.ascontiguousarray(features.directions, dtype=np.float64).reshape(-1, 2, 2),
        np.ascontiguousarray(features.segment_ids, dtype=np.int64).reshape(-1, 2),
        np.ascontiguousarray(features.seg_endpoints, dtype=np.float64).reshape(-1, 2, 2),
        float(offset_m),
        INTERSECTION,
        _MIN_NORM,
    )


class VisibilityInputs(NamedTuple):
    """What the map update's visibility test reads of a new scan alone (pose-independent;
    computed ahead in a feature worker by :mod:`iceg.scan_products`).

    Attributes:
        support_offset_m: The ``FeatureMapConfig.support_offset_m`` of ``geometry``.
        geometry: The features' visibility geometry (see :func:`_geometry`).
        beams: The scan's beams by bearing (:meth:`_BeamProfile.of_scan`).
    """

    support_offset_m: float
    geometry: _VisibilityGeometry
    beams: _BeamProfile


def visibility_inputs(
    features: ScanFeatures, scan: LaserScan, support_offset_m: float
) -> VisibilityInputs:
    """The :class:`VisibilityInputs` of a scan and its features, as an update computes them."""
    return VisibilityInputs(
        support_offset_m, _geometry(features, support_offset_m), _BeamProfile.of_scan(scan)
    )


#: Visibility inputs computed ahead (:func:`remember_visibility_inputs`), by features object,
#: with the scan object they belong to (dropped with the features).
_AHEAD: weakref.WeakKeyDictionary[ScanFeatures, tuple[LaserScan, VisibilityInputs]] = (
    weakref.WeakKeyDictionary()
)


def remember_visibility_inputs(
    features: ScanFeatures, scan: LaserScan, inputs: VisibilityInputs
) -> None:
    """Let an update of ``features`` with ``scan`` use ``inputs``, which
    :func:`visibility_inputs` computed for them (or for copies of them, bit for bit: a
    worker's), instead of computing them again."""
    _AHEAD[features] = (scan, inputs)


class FeatureMap:
    """Landmarks anchored to graph nodes, with time-validity (paper §III-C3).

    Typical use, per keyframe (see ``iceg.slam``)::

        ref = fmap.reference(node_poses, recent_node_ids, node_poses[last])
        res = matcher.match(features, ref.features, prediction, bounds)
        # ... add the node and factors, update the graph ...
        fmap.update(
            new_id, features, scan.stamp_s, reference=ref, match=res, scan=scan,
            node_poses=updated_node_poses,
        )

    Args:
        config: Feature-map configuration.
    """

    def __init__(self, config: FeatureMapConfig | None = None) -> None:
        self.config = config or FeatureMapConfig()
        self._lm = _Landmarks.empty()
        self._seg = _Segments.empty()
        self._pts = _Points.empty()
        self._touched = _Touched.empty()
        # Each node's segments, points and touched landmarks are one contiguous block of rows:
        # node -> [start, stop).
        self._seg_rows: dict[int, tuple[int, int]] = {}
        self._pts_rows: dict[int, tuple[int, int]] = {}
        self._touched_rows: dict[int, tuple[int, int]] = {}
        self._nodes: set[int] = set()
        self._next_id = 0
        self.n_merged = 0
        self._range_max_m = _DEFAULT_RANGE_MAX_M
        self._last_stamp_s = 0.0
        self._token = object()  # identifies the references this map built
        self._pruned: list[PrunedLandmarks] = []
        # The last scan's visibility geometry (_geometry), read twice per update.
        self._geometry_memo: tuple[ScanFeatures, _VisibilityGeometry] | None = None
        # The last _chosen answer (the nodes' bytes, the rows): a reference reads it twice,
        # for its pose nodes and for its landmarks; an update forgets it.
        self._chosen_memo: tuple[bytes, IntArray] | None = None
        # The last _taking_part answer (node id, the reference ids' bytes, the rows): an
        # update's pose nodes and its bookkeeping read it; the bookkeeping forgets it.
        self._part_memo: tuple[int, bytes | None, IntArray] | None = None

    # ------------------------------------------------------------------ inspection
    def __len__(self) -> int:
        """Number of landmarks."""
        return len(self._lm)

    def __repr__(self) -> str:
        kinds = np.bincount(self._lm.kind, minlength=len(FeatureKind))
        n_pruned = sum(p.ids.shape[0] for p in self._pruned)
        return (
            f"FeatureMap(nodes={len(self._nodes)}, landmarks={len(self)} "
            f"[corner={kinds[CORNER]}, eow={kinds[EOW]}, intersection={kinds[INTERSECTION]}], "
            f"segments={len(self._seg)}, pruned={n_pruned}, merged={self.n_merged})"
        )

    @property
    def node_ids(self) -> IntArray:
        """Sorted ids of the nodes added so far."""
        return np.array(sorted(self._nodes), dtype=np.int64)

    @property
    def pruned(self) -> PrunedLandmarks:
        """Every landmark pruned so far (positions in their anchor's frame)."""
        if not self._pruned:
            return PrunedLandmarks(
                **{k: np.zeros((0, *shape), dtype=dt) for k, (dt, shape) in _PRUNED_SPEC.items()}
            )
        return PrunedLandmarks(
            **{k: np.concatenate([getattr(p, k) for p in self._pruned]) for k in _PRUNED_SPEC}
        )

    # ------------------------------------------------------------------ state (sessions)
    def export_state(self) -> dict[str, np.ndarray]:
        """The whole map as named arrays, for a columnar file (``iceg.session``; no pickle).

        Keys: ``lm_<field>`` (landmarks, :class:`_Landmarks` fields, geometry in the anchor
        node's frame), ``seg_<field>`` (segments), ``pts_<field>`` (kept points),
        ``pruned_<field>`` (:class:`PrunedLandmarks`), ``nodes`` ``(K,)`` int64 and
        ``scalars`` ``(4,)`` float64 ``[next_id, n_merged, range_max_m, last_stamp_s]``.
        Arrays are copies; :meth:`from_state` rebuilds an identical map.
        """
        out: dict[str, np.ndarray] = {}
        for prefix, cols in (("lm", self._lm), ("seg", self._seg), ("pts", self._pts)):
            for f in fields(cols):
                out[f"{prefix}_{f.name}"] = np.array(getattr(cols, f.name), copy=True)
        pruned = self.pruned
        for k in _PRUNED_SPEC:
            out[f"pruned_{k}"] = np.array(getattr(pruned, k), copy=True)
        out["nodes"] = np.array(sorted(self._nodes), dtype=np.int64)
        out["scalars"] = np.array(
            [self._next_id, self.n_merged, self._range_max_m, self._last_stamp_s], dtype=np.float64
        )
        return out

    @classmethod
    def from_state(
        cls, state: Mapping[str, np.ndarray], config: FeatureMapConfig | None = None
    ) -> FeatureMap:
        """Rebuild a map written by :meth:`export_state` (same arrays, same later updates).

        Raises:
            FeatureMapError: a key is missing or an array has the wrong dtype or shape.
        """
        fmap = cls(config)
        containers = (("lm", _Landmarks), ("seg", _Segments), ("pts", _Points))
        try:
            for prefix, kind in containers:
                cols = {
                    k: _state_array(state, f"{prefix}_{k}", dt, sh)
                    for k, (dt, sh) in kind.SPEC.items()
                }
                setattr(fmap, f"_{prefix}", kind(**cols))
            pruned = {
                k: _state_array(state, f"pruned_{k}", dt, sh)
                for k, (dt, sh) in _PRUNED_SPEC.items()
            }
            nodes = _state_array(state, "nodes", np.int64, ())
            scalars = _state_array(state, "scalars", np.float64, ())
        except KeyError as exc:
            raise FeatureMapError(f"FeatureMap.from_state: missing array {exc}") from None
        if scalars.shape != (4,):
            raise FeatureMapError(
                f"FeatureMap.from_state: scalars must be (4,), got {scalars.shape}"
            )
        fmap._seg_rows = _node_blocks(fmap._seg.node)
        fmap._pts_rows = _node_blocks(fmap._pts.node)
        fmap._index_touched()
        fmap._pruned = [PrunedLandmarks(**pruned)] if pruned["ids"].shape[0] else []
        fmap._nodes = {int(n) for n in nodes}
        fmap._next_id, fmap.n_merged = int(scalars[0]), int(scalars[1])
        fmap._range_max_m, fmap._last_stamp_s = float(scalars[2]), float(scalars[3])
        return fmap

    def checkpoint(self) -> MapCheckpoint:
        """The map's state now, to :meth:`restore` after updates that are to be undone (a
        speculative update, :mod:`iceg.slam`). Costs a copy of the landmark table (and a
        restore another)."""
        return MapCheckpoint(
            self._lm.copy(),
            self._token,
            (len(self._seg), len(self._pts), len(self._touched)),
            (len(self._seg_rows), len(self._pts_rows), len(self._touched_rows)),
            len(self._pruned),
            (self._next_id, self.n_merged, self._range_max_m, self._last_stamp_s),
        )

    def restore(self, checkpoint: MapCheckpoint) -> None:
        """Undo every :meth:`update` since ``checkpoint``: the map answers and updates as if
        they had never run, bit for bit (the checkpoint stays valid for another restore).

        Raises:
            FeatureMapError: the checkpoint was taken from another map.
        """
        if checkpoint.map_token is not self._token:
            raise FeatureMapError("FeatureMap.restore: the checkpoint is another map's")
        self._lm = checkpoint.landmarks.copy()
        tables = (self._seg, self._pts, self._touched)
        for table, n in zip(tables, checkpoint.n_rows, strict=True):
            table.truncate(n)
        blocks = (self._seg_rows, self._pts_rows, self._touched_rows)
        for rows, n in zip(blocks, checkpoint.n_blocks, strict=True):
            while len(rows) > n:
                node, _ = rows.popitem()  # the newest block first
                self._nodes.discard(node)
        del self._pruned[checkpoint.n_pruned :]
        self._next_id, self.n_merged, self._range_max_m, self._last_stamp_s = checkpoint.scalars
        self._chosen_memo = self._part_memo = None

    def world_landmarks(self, node_poses: NodePoses) -> LandmarkView:
        """All landmarks whose anchor has a pose, expressed in the frame of ``node_poses``
        (the map/world frame of the graph estimates).

        Args:
            node_poses: ``{node_id: (3,) pose}`` or ``(ids (N,), poses (N, 3))``.

        Raises:
            FeatureMapError: ``node_poses`` holds different numbers of ids and poses.
        """
        ids, poses = _node_pose_table(node_poses)
        pos, found = lookup_sorted(ids, self._lm.anchor)
        sel = np.flatnonzero(found)
        return self._lm.in_frame(sel, poses[pos[sel]])

    def world_segments(self, node_poses: NodePoses) -> tuple[FloatArray, IntArray]:
        """Every stored segment (wall) of the nodes that have a pose, in the frame of
        ``node_poses`` (the map frame of the graph estimates).

        Args:
            node_poses: ``{node_id: (3,) pose}`` or ``(ids (N,), poses (N, 3))``.

        Returns:
            ``(endpoints, nodes)``: ``(M, 2, 2)`` float64 endpoints (metres) and ``(M,)``
            int64 the node that saw each segment.

        Raises:
            FeatureMapError: ``node_poses`` holds different numbers of ids and poses.
        """
        ids, poses = _node_pose_table(node_poses)
        pos, found = lookup_sorted(ids, self._seg.node)
        sel = np.flatnonzero(found)
        endpoints, _, _ = self._seg.in_frame(sel, poses[pos[sel]])
        return endpoints, self._seg.node[sel]

    # ------------------------------------------------------------------ reference
    def reference(
        self,
        node_poses: NodePoses,
        node_ids: Sequence[int] | ArrayLike,
        frame_pose: ArrayLike,
    ) -> MapReference:
        """Build a matching reference from chosen nodes (recent ones for tracking, older
        ones near the current estimate for loop closure; docs/design.md "Feature map").

        It holds the landmarks anchored to ``node_ids`` or last matched from one of them,
        and the segments of those nodes, all in the frame of ``frame_pose``.

        Args:
            node_poses: Current pose estimates ``{node_id: (3,) pose}`` or
                ``(ids (N,), poses (N, 3))``, map frame; must include the anchors used.
            node_ids: Nodes whose landmarks and segments to use.
            frame_pose: ``(3,)`` pose (map frame) of the reference frame, usually the pose
                of the newest of ``node_ids``.

        Returns:
            A :class:`MapReference`: its ``features`` are in the frame of ``frame_pose``;
            ``ids`` are landmark ids; ``segment_ids`` -1; ``points_xy`` holds the nodes' scan
            points (with ``seg_point_range`` into them) when ``config.reference_points``,
            else it is empty and ``seg_point_range`` -1. It keeps the pose snapshot.

        Raises:
            FeatureMapError: ``node_poses`` holds different numbers of ids and poses.
        """
        frame = np.asarray(frame_pose, dtype=np.float64).reshape(3)
        ids, poses = _node_pose_table(node_poses)
        want = sorted_unique(node_ids)
        _, posed = lookup_sorted(ids, want)
        want_posed = want[posed]  # nodes whose segments and points can be placed
        ssel = _block_rows(self._seg_rows, want_posed)
        lm, seg = self._lm, self._seg
        rows, xy, cov, directions, ep, lines, lcov = reference_geometry(
            ids,
            poses,
            frame_inverse(frame),
            self._chosen(want),
            lm.anchor,
            lm.xy,
            lm.cov,
            lm.dirs,
            ssel,
            seg.node,
            seg.ep,
            seg.lines,
            seg.cov,
        )
        points, seg_pr = self._reference_points(ids, poses, want_posed, frame, ssel)
        features = ScanFeatures(
            points_xy=points,
            seg_endpoints=ep,
            seg_lines=lines,
            seg_cov=lcov,
            seg_point_range=seg_pr,
            kind=lm.kind[rows],
            xy=xy,
            cov=cov,
            directions=directions,
            opening_rad=lm.opening[rows],
            segment_ids=np.full((rows.shape[0], 2), -1, dtype=np.int64),
            ids=lm.id[rows],
            range_max_m=self._range_max_m,
            stamp_s=self._last_stamp_s,
        )
        return MapReference(features, frame, ids, poses, self._token)

    def reference_pose_nodes(self, node_ids: Sequence[int] | ArrayLike) -> IntArray:
        """The nodes whose poses :meth:`reference` reads for ``node_ids``: those nodes and the
        anchors of their landmarks. A pose table holding (at least) these gives the same
        reference as a table of every node.

        Returns:
            ``(k,)`` int64 sorted node ids.
        """
        want = sorted_unique(node_ids)
        return sorted_union(want, self._lm.anchor[self._chosen(want)])

    def update_pose_nodes(self, node_id: int, reference: MapReference | None) -> IntArray:
        """The nodes whose poses :meth:`update` reads for the new node ``node_id`` matched
        against ``reference``: the node and the anchors of the landmarks taking part in its
        bookkeeping. A ``node_poses`` table holding (at least) these gives the same update as
        a table of every node.

        Returns:
            ``(k,)`` int64 sorted node ids.
        """
        ref_ids = None if reference is None else reference.landmark_ids
        anchors = self._lm.anchor[self._taking_part(int(node_id), ref_ids)]
        return sorted_union(np.array([int(node_id)], dtype=np.int64), anchors)

    def _chosen(self, want: IntArray) -> IntArray:
        """Ascending rows of the landmarks anchored to or last matched from the nodes
        ``want`` (sorted unique ids). In a large map, among the landmarks those nodes touched
        (:class:`_Touched`), so the cost is what the nodes hold, not what the map holds.
        Read-only: the answer is kept until the next question or update."""
        key = want.tobytes()
        if self._chosen_memo is not None and self._chosen_memo[0] == key:
            return self._chosen_memo[1]
        lm = self._lm
        if len(lm) < _TOUCHED_FROM_LANDMARKS:
            rows = rows_of_nodes(want, lm.anchor, lm.last_node)
        else:
            touched = self._touched.id[_block_rows(self._touched_rows, want)]
            pos, found = lookup_sorted(lm.id, touched)
            rows = pos[found]  # ids ascending with the rows
            nodes = np.concatenate([lm.anchor[rows], lm.last_node[rows]])
            keep = lookup_sorted(want, nodes)[1].reshape(2, -1).any(axis=0)
            rows = np.unique(rows[keep])
        rows.flags.writeable = False
        self._chosen_memo = (key, rows)
        return rows

    def _touch(self, node_id: int, landmark_ids: IntArray) -> None:
        """Record the landmarks a new node created or matched (:class:`_Touched`)."""
        start = len(self._touched)
        self._touched_rows[node_id] = (start, start + landmark_ids.shape[0])
        self._touched.extend(landmark_ids.shape[0], id=landmark_ids)

    def _index_touched(self) -> None:
        """Rebuild the :class:`_Touched` blocks from the landmarks' anchors and last
        matching nodes (a map read back from its state)."""
        lm = self._lm
        nodes = np.concatenate([lm.anchor, lm.last_node])
        ids = np.concatenate([lm.id, lm.id])
        order = np.lexsort((ids, nodes))
        nodes, ids = nodes[order], ids[order]
        distinct = np.r_[True, (nodes[1:] != nodes[:-1]) | (ids[1:] != ids[:-1])]
        self._touched = _Touched.empty()
        self._touched.extend(int(distinct.sum()), id=ids[distinct])
        self._touched_rows = _node_blocks(nodes[distinct])

    def _taking_part(self, node_id: int, reference_ids: IntArray | None) -> IntArray:
        """Ascending rows of the landmarks taking part in the bookkeeping of the new node
        ``node_id``: all, or with ``bookkeeping_recent_nodes`` those last matched (or
        created) from the recent nodes and those of the reference (ids
        ``reference_ids``). Read-only: the answer is kept until the next question or the
        update's bookkeeping."""
        key = None if reference_ids is None else reference_ids.tobytes()
        memo = self._part_memo
        if memo is not None and memo[0] == node_id and memo[1] == key:
            return memo[2]
        lm = self._lm
        if self.config.bookkeeping_recent_nodes is None:
            rows = np.arange(len(lm), dtype=np.int64)
        else:
            rows = rows_taking_part(
                lm.last_node,
                node_id - self.config.bookkeeping_recent_nodes,
                lm.id,
                _NO_IDS if reference_ids is None else reference_ids,
            )
        rows.flags.writeable = False
        self._part_memo = (node_id, key, rows)
        return rows

    def _reference_points(
        self, ids: IntArray, poses: FloatArray, want: IntArray, frame: FloatArray, ssel: IntArray
    ) -> tuple[FloatArray, IntArray]:
        """Scan points of ``want`` (nodes with a pose in ``ids``) in the frame ``frame`` and
        each chosen segment's ``[start, stop)`` into them (-1 without points)."""
        points = np.zeros((0, 2))
        seg_pr = np.full((ssel.shape[0], 2), -1, dtype=np.int64)
        if not (self.config.reference_points and len(self._pts)):
            return points, seg_pr
        sg, pt = self._seg, self._pts
        psel = _block_rows(self._pts_rows, want)
        ppos, _ = lookup_sorted(ids, pt.node[psel])
        prel = poses_in_frame(frame, poses, ppos)
        points = move_points(prel, pt.xy[psel][:, None, :], True)[:, 0]
        # Each node's points are contiguous: shift its segments' ranges to its block.
        nodes_sel, first = np.unique(pt.node[psel], return_index=True)
        k = np.searchsorted(nodes_sel, sg.node[ssel])
        k = np.clip(k, 0, max(nodes_sel.shape[0] - 1, 0))
        has = (nodes_sel.shape[0] > 0) & (sg.pr[ssel, 0] >= 0)
        if nodes_sel.shape[0]:
            has &= nodes_sel[k] == sg.node[ssel]
        seg_pr = np.where(has[:, None], sg.pr[ssel] + first[k][:, None], -1)
        return points, seg_pr

    # ------------------------------------------------------------------ update
    def update(
        self,
        node_id: int,
        features: ScanFeatures,
        stamp_s: float,
        *,
        reference: MapReference | None = None,
        match: MatchResult | None = None,
        scan: LaserScan | None = None,
        node_poses: NodePoses | None = None,
        node_pose: ArrayLike | None = None,
    ) -> MapUpdate:
        """Add a node's scan to the map: association, new landmarks, time-validity.

        With a successful ``match`` against ``reference`` (built by :meth:`reference`):

        - the matcher's inlier pairs give the landmarks this scan matched; every other
          landmark whose anchor has a pose is brought into the new node's frame and
          associated with an unpaired new feature within ``association_gate_m`` (of any
          kind: a Corner seen partially is an EOW, paper §III-C2, or an Intersection of its
          two walls);
        - a matched landmark keeps the more precise observation, and takes the kind of an
          observation that tells more (Corner > EOW > Intersection);
        - every landmark **expected** in this scan (support points inside its field of view
          and ``expected_max_range_m``, not occluded by its own ranges, walls not at grazing
          incidence) but not matched counts a miss; then pruning runs (paper §III-C3);
        - the remaining new features become landmarks anchored to ``node_id``.

        Without a successful match (first node, failed match) every feature becomes a new
        landmark anchored to ``node_id`` and no bookkeeping is done (the node's pose relative
        to the map is not known well enough to judge visibility).

        Args:
            node_id: The new node's id (each node is added once).
            features: The node's scan features, robot frame (= node frame).
            stamp_s: Scan time, seconds.
            reference: The reference ``match`` was computed against.
            match: The match of ``features`` against ``reference.features``.
            scan: The laser scan, for visibility (field of view, occlusion by its own
                ranges); ``None`` uses ``features.points_xy`` instead.
            node_poses: Current pose estimates of the nodes (map frame), to place every
                landmark relative to the new node; ``None`` uses the poses given to
                :meth:`reference` and ``frame_pose ∘ match.pose`` for the new node.
            node_pose: ``(3,)`` map-frame pose of the new node, when ``node_poses`` does not
                hold it (default ``frame_pose ∘ match.pose``).

        Returns:
            A :class:`MapUpdate`.

        Raises:
            FeatureMapError: ``node_id`` was already added, or a successful ``match`` comes
                without a ``reference`` built by this map.
        """
        node_id = int(node_id)
        if node_id in self._nodes:
            raise FeatureMapError(f"FeatureMap.update: node {node_id} was already added")
        self._chosen_memo = None  # the rows and their anchors change
        stamp = float(stamp_s)
        empty = np.zeros(0, dtype=np.int64)
        if match is not None and match.success:
            ref = self._own(reference)
            book = self._bookkeep(node_id, features, stamp, ref, match, scan, node_poses, node_pose)
        else:
            book = _Bookkeeping(empty, empty, np.ones(features.n_features, dtype=bool), empty)
        self._part_memo = None  # the bookkeeping and what follows change the rows
        merged_ids = self._merge(book.merge_rows) if book.merge_rows.shape[0] else empty
        self._store_segments(node_id, features)
        added = self._add_landmarks(node_id, features, book.new_mask, stamp)
        self._touch(node_id, np.concatenate([book.matched_ids, added]))
        pruned = self._prune(stamp)
        self._nodes.add(node_id)
        self._range_max_m = float(features.range_max_m)
        self._last_stamp_s = stamp
        return MapUpdate(node_id, book.matched_ids, added, book.expected_ids, pruned, merged_ids)

    def _own(self, reference: MapReference | None) -> MapReference:
        if not isinstance(reference, MapReference) or reference.map_token is not self._token:
            raise FeatureMapError(
                "FeatureMap.update: a successful match needs reference=<the MapReference "
                "returned by this map's reference() that match() was computed against>"
            )
        return reference

    def _merge(self, merge_rows: IntArray) -> IntArray:
        """Remove duplicate landmarks (merged into a matched one); return their ids."""
        merged_ids = self._lm.id[merge_rows].copy()
        self._lm.drop(merge_rows)
        self.n_merged += int(merge_rows.shape[0])
        return merged_ids

    def _store_segments(self, node_id: int, features: ScanFeatures) -> None:
        m = features.n_segments
        keep = self.config.reference_points
        start = len(self._seg)
        self._seg_rows[node_id] = (start, start + m)
        self._seg.extend(
            m,
            node=node_id,
            ep=np.asarray(features.seg_endpoints, dtype=np.float64).reshape(m, 2, 2),
            lines=np.asarray(features.seg_lines, dtype=np.float64).reshape(m, 2),
            cov=np.asarray(features.seg_cov, dtype=np.float64).reshape(m, 2, 2),
            pr=np.asarray(features.seg_point_range, dtype=np.int64).reshape(m, 2) if keep else -1,
        )
        if keep:
            pts = np.asarray(features.points_xy, dtype=np.float64).reshape(-1, 2)
            start = len(self._pts)
            self._pts_rows[node_id] = (start, start + pts.shape[0])
            self._pts.extend(pts.shape[0], node=node_id, xy=pts)

    def _add_landmarks(
        self, node_id: int, features: ScanFeatures, mask: BoolArray, stamp: float
    ) -> IntArray:
        rows = np.flatnonzero(mask)
        n = rows.shape[0]
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        support, wall_p, wall_d, wall_side = (a[rows] for a in self._geometry_of(features))
        self._lm.extend(
            n,
            id=ids,
            anchor=node_id,
            kind=np.asarray(features.kind, dtype=np.int64)[rows],
            xy=features.xy[rows],
            cov=features.cov[rows],
            dirs=features.directions[rows],
            opening=features.opening_rad[rows],
            support=support,
            wall_p=wall_p,
            wall_d=wall_d,
            wall_side=wall_side,
            n_expected=0,
            n_matched=0,
            misses=0,
            created_s=stamp,
            last_matched_s=stamp,
            first_miss_s=np.nan,
            last_node=node_id,
        )
        return ids

    # ------------------------------------------------------------------ bookkeeping
    def _bookkeep(
        self,
        node_id: int,
        features: ScanFeatures,
        stamp: float,
        reference: MapReference,
        match: MatchResult,
        scan: LaserScan | None,
        node_poses: NodePoses | None,
        node_pose: ArrayLike | None,
    ) -> _Bookkeeping:
        """Association and expected/matched counting for one matched scan; also finds the
        rows of duplicate landmarks to merge."""
        near, pair_new, pair_row, merge_rows = self._associate(
            node_id, features, reference, match, node_poses, node_pose
        )
        new_mask = np.ones(features.n_features, dtype=bool)
        new_mask[pair_new] = False
        if pair_row.shape[0]:
            self._keep_better(features, near, pair_new, pair_row)
        expected = self._expected(near.rows, near.anchor_in_new, features, scan)
        matched_rows, exp_rows = self._count(near.rows, expected, pair_row, stamp, node_id)
        return _Bookkeeping(
            self._lm.id[matched_rows].copy(), self._lm.id[exp_rows].copy(), new_mask, merge_rows
        )

    def _associate(
        self,
        node_id: int,
        features: ScanFeatures,
        reference: MapReference,
        match: MatchResult,
        node_poses: NodePoses | None,
        node_pose: ArrayLike | None,
    ) -> tuple[_Near, IntArray, IntArray, IntArray]:
        """The landmarks taking part (restricted to the reference's and recently matched ones
        by ``bookkeeping_recent_nodes``) whose anchor has a pose, in the new node's frame; the
        pairs (new feature, landmark row): the matcher's, then each unpaired feature with the
        nearest unpaired landmark within ``association_gate_m``; and the rows of the other
        landmarks within the gate of a paired feature (the same physical feature anchored to
        another node: they merge into the paired one). One compiled pass
        (:func:`~iceg.landmark_association.associate_scan`)."""
        lm = self._lm
        if node_poses is not None:
            tab_ids, tab_poses = _node_pose_table(node_poses)
        else:
            tab_ids, tab_poses = reference.node_ids, reference.node_poses
        npos, nfound = lookup_sorted(tab_ids, np.array([node_id]))
        if nfound[0]:
            new_pose = tab_poses[npos[0]]
        elif node_pose is not None:
            new_pose = np.asarray(node_pose, dtype=np.float64).reshape(3)
        else:
            new_pose = compose(reference.frame_pose, match.pose)
        rows, anchor_in_new, xy_new, slot, pair_new, pair_row, merge_rows = associate_scan(
            self._taking_part(node_id, reference.landmark_ids),
            lm.id,
            lm.anchor,
            lm.xy,
            tab_ids,
            np.ascontiguousarray(tab_poses, dtype=np.float64),
            frame_inverse(new_pose),
            np.ascontiguousarray(np.asarray(match.inlier_pairs, dtype=np.int64).reshape(-1, 2)),
            reference.landmark_ids,
            np.ascontiguousarray(features.xy, dtype=np.float64).reshape(-1, 2),
            float(self.config.association_gate_m),
        )
        return _Near(rows, anchor_in_new, xy_new, slot), pair_new, pair_row, merge_rows

    def _keep_better(
        self, features: ScanFeatures, near: _Near, pair_new: IntArray, pair_row: IntArray
    ) -> None:
        """Keep the better observation of each paired landmark: a new one replaces the stored
        one when its covariance trace is below ``replace_ratio`` of it, or when it tells
        more (an EOW seen as a Corner becomes a Corner); moved into the anchor's frame, with
        the side of each wall the new node saw it from (:func:`keep_better`, compiled)."""
        lm = self._lm
        support, wall_p, wall_d, _ = self._geometry_of(features)
        keep_better(
            pair_new,
            pair_row,
            np.ascontiguousarray(near.anchor_in_new[near.slot[pair_row]]),
            _RANK,
            float(self.config.replace_ratio),
            FeatureRows(
                np.ascontiguousarray(features.xy, dtype=np.float64),
                np.ascontiguousarray(features.cov, dtype=np.float64),
                np.ascontiguousarray(features.directions, dtype=np.float64),
                np.ascontiguousarray(features.opening_rad, dtype=np.float64),
                np.ascontiguousarray(features.kind, dtype=np.int64),
                support,
                wall_p,
                wall_d,
            ),
            FeatureRows(
                lm.xy, lm.cov, lm.dirs, lm.opening, lm.kind, lm.support, lm.wall_p, lm.wall_d
            ),
            lm.wall_side,
        )

    def _geometry_of(self, features: ScanFeatures) -> _VisibilityGeometry:
        """:func:`_geometry` of a scan's features, computed once per features object (an
        update's replacements and its new landmarks both read it; features are never
        modified after extraction)."""
        ahead = _AHEAD.get(features)
        if ahead is not None and ahead[1].support_offset_m == self.config.support_offset_m:
            return ahead[1].geometry
        memo = self._geometry_memo
        if memo is None or memo[0] is not features:
            memo = self._geometry_memo = (
                features,
                _geometry(features, self.config.support_offset_m),
            )
        return memo[1]

    def _count(
        self, rows: IntArray, expected: BoolArray, pair_row: IntArray, stamp: float, node_id: int
    ) -> tuple[IntArray, IntArray]:
        """Expected / matched / miss counters (:func:`~iceg.visibility.count_observations`);
        returns the matched and expected rows."""
        lm = self._lm
        return count_observations(
            rows,
            expected,
            pair_row,
            float(stamp),
            int(node_id),
            lm.n_expected,
            lm.n_matched,
            lm.misses,
            lm.first_miss_s,
            lm.last_matched_s,
            lm.last_node,
        )

    # ------------------------------------------------------------------ visibility
    def _expected(
        self,
        rows: IntArray,
        anchor_in_new: FloatArray,
        features: ScanFeatures,
        scan: LaserScan | None,
    ) -> BoolArray:
        """Which landmarks (``rows``, anchors at ``anchor_in_new`` in the new frame) the scan
        should see (docs/design.md: inside the field of view and range, not occluded; and its walls
        (one for a Corner or EOW, both for an Intersection) seen from the side they were seen
        from before, not at grazing incidence)."""
        lm = self._lm
        n = rows.shape[0]
        if n == 0:
            return np.zeros(0, dtype=bool)
        ahead = _AHEAD.get(features)
        if scan is None:
            profile = _BeamProfile.of_points(features.points_xy)
        elif ahead is not None and ahead[0] is scan:
            profile = ahead[1].beams
        else:
            profile = _BeamProfile.of_scan(scan)
        if profile.bearing.shape[0] == 0:
            return np.zeros(n, dtype=bool)
        cfg = self.config
        return expected_landmarks(
            rows,
            anchor_in_new,
            lm.support,
            lm.wall_p,
            lm.wall_d,
            lm.wall_side,
            lm.kind,
            INTERSECTION,
            profile.bearing,
            profile.range_m,
            _MAX_GAP_BEAMS * profile.spacing_rad,
            profile.sensor_pose if profile.sensor_pose is not None else np.zeros(0),
            math.radians(cfg.fov_margin_deg),
            cfg.expected_max_range_m,
            cfg.occlusion_tolerance_m,
            math.sin(math.radians(cfg.min_incidence_deg)),
        )

    # ------------------------------------------------------------------ pruning
    def _prune(self, stamp: float) -> IntArray:
        """Ratio and time-validity pruning (paper §III-C3); returns the pruned ids."""
        cfg, lm = self.config, self._lm
        d, stale = pruned_landmarks(
            lm.n_expected,
            lm.n_matched,
            lm.misses,
            lm.last_matched_s,
            lm.first_miss_s,
            float(stamp),
            cfg.min_expected,
            cfg.min_match_ratio,
            cfg.min_misses,
            cfg.validity_s,
            cfg.miss_confirm_s,
        )
        if d.shape[0] == 0:
            return d
        self._pruned.append(
            PrunedLandmarks(
                ids=lm.id[d],
                anchor=lm.anchor[d],
                kind=lm.kind[d],
                xy=lm.xy[d],
                stamp_s=np.full(d.shape[0], stamp),
                created_s=lm.created_s[d],
                last_matched_s=lm.last_matched_s[d],
                reason=np.where(stale, PRUNED_VALIDITY, PRUNED_RATIO).astype(np.int64),
            )
        )
        lm.drop(d)
        log.debug("pruned %d landmarks at %.2f s", d.shape[0], stamp)
        return self._pruned[-1].ids


__all__ = [
    "PRUNED_RATIO",
    "PRUNED_VALIDITY",
    "FeatureMap",
    "FeatureMapConfig",
    "LandmarkView",
    "MapCheckpoint",
    "MapReference",
    "MapUpdate",
    "PrunedLandmarks",
]
