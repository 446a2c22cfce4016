"""ROS 1 and ROS 2 bags without ROS: a streaming reader (LaserScan, Odometry, tf) and a writer.

Bags are opened with ``rosbags.highlevel.AnyReader`` (the ``ros`` extra): ROS 1 ``.bag`` files,
ROS 2 bag folders (``metadata.yaml``) and raw ``.db3`` / ``.mcap`` files; where a bag embeds no
definition of the types read (:data:`READ_TYPES`), the Humble (ROS 2) or Noetic (ROS 1)
typestore's are used. A bag of any size is read message by message: one survey pass over the
topic list, ``/tf_static`` and ``/tf`` (frames, mounting), then one pass over the scan and
odometry messages.

Conventions (REP 103 / REP 105 / REP 117):

- ``stamp_s`` is the scan's ``header.stamp`` (not the bag's receive time), read exactly as
  ``(sec * 10**9 + nanosec) / 10**9``: a float stamp written with :func:`stamp_ns` reads back
  bit for bit.
- Odometry is ``nav_msgs/Odometry`` (``pose.pose``), or the ``/tf`` transform from the odom
  frame to the robot base frame, SE(2)-interpolated at the scan's stamp (the geodesic
  ``p0 ∘ exp(f · log(p0⁻¹ p1))``, Barfoot, *State Estimation for Robotics*, 2017, §7.1.7).
  A scan outside the odometry's time span gets ``odom_pose=None`` and is counted in
  :attr:`RosbagReader.scans_without_odometry` (one warning at the end).
- The laser mounting pose is the tf chain base frame → the scan's ``frame_id``
  (``/tf_static``, else the first ``/tf`` value), projected to SE(2). A bag with no odometry
  whose tf names no laser frame has one frame only: the laser's is the base (identity mounting,
  a warning; the trajectory is the laser's). A laser tilted more than
  ``max_laser_tilt_rad`` is refused; an upside-down laser (z axis down) is handled by mirroring
  its bearings (``a -> -a``, beams reversed so bearings increase).
- ROS stores ranges and angles as float32. They are widened to the *simplest* float64 that
  rounds to the stored float32: ranges to the shortest decimal (what ``rostopic echo``
  prints), angles to a multiple ``p·π/q`` (``q <= 1440``) if one rounds to them, else the
  shortest decimal. Both lie within half a float32 ulp of the stored value, and decimal- or
  π-based logs (CARMEN) round-trip exactly.
- Invalid ranges (NaN, ±inf, below ``range_min``) become ``+inf``, a no-return beam, as the
  CARMEN reader stores NaN; ranges at or above ``range_max`` are kept (already no-return).
"""

from __future__ import annotations

import bisect
import functools
import logging
import math
from collections import Counter, deque
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import NDArray

from frontends.registry import register_reader
from frontends.scan import LaserScan, StampPolicy, StampReport, order_by_stamp
from iceg_common import se2
from iceg_common.errors import ConfigError, LogFormatError, ScanError

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

SCAN_TYPES = ("sensor_msgs/msg/LaserScan", "sensor_msgs/msg/MultiEchoLaserScan")
ODOM_TYPE = "nav_msgs/msg/Odometry"
TF_TYPE = "tf2_msgs/msg/TFMessage"
#: The message types the reader deserializes; a bag's other topics are read from its index.
READ_TYPES = (*SCAN_TYPES, ODOM_TYPE, TF_TYPE)
TF_TOPICS = ("/tf", "/tf_static")
#: Default largest tilt of the laser plane from the base's x-y plane that is projected to SE(2).
MAX_LASER_TILT_RAD = math.radians(5.0)
#: Largest denominator ``q`` of an angle ``p·π/q`` recovered from a float32 (1440: 0.125 deg).
_PI_DENOMINATOR = 1440
_MAX_DECIMALS = 12
_ODOM_HISTORY = 512
_INSTALL_HINT = "reading ROS bags needs the 'ros' extra: pip install 'iceg[ros]' (rosbags)"
_ROS2_SUFFIXES = (".db3", ".mcap")


# ---------------------------------------------------------------------------------------------
# Numbers: exact stamps, float32 widening, quaternions, SE(2) interpolation
# ---------------------------------------------------------------------------------------------


def stamp_ns(stamp_s: float) -> int:
    """Nanoseconds nearest to the exact value of the float ``stamp_s`` (no float rounding).

    ``stamp_ns(t) / 10**9 == t`` (a correctly rounded integer quotient) for every ``t`` with
    ``2**23 <= |t| < 2**62 / 10**9`` (any epoch stamp: the float's ulp is at least 2 ns) and
    for every ``t`` written with at most 9 decimals (e.g. simulation time ``0.565``).
    """
    return round(Fraction(stamp_s) * 10**9)


def _stamp_s(sec: int, nanosec: int) -> float:
    return (int(sec) * 10**9 + int(nanosec)) / 10**9


def widen_decimal(values: NDArray[np.float32]) -> FloatArray:
    """float32 -> the float64 of the shortest decimal (<= 12 places) that rounds to each value.

    Args:
        values: ``(N,)`` float32 (any shape works).

    Returns:
        float64 array of the same shape; non-finite values, zeros and values with no such
        decimal are widened as is.
    """
    v32 = np.asarray(values, dtype=np.float32)
    v = v32.astype(np.float64)
    out = v.copy()
    todo = np.isfinite(v) & (v != 0.0)
    for places in range(_MAX_DECIMALS + 1):
        idx = np.flatnonzero(todo)
        if idx.size == 0:
            break
        scale = 10.0**places
        cand = np.rint(v[idx] * scale) / scale
        ok = cand.astype(np.float32) == v32[idx]
        out[idx[ok]] = cand[ok]
        todo[idx[ok]] = False
    return out


def widen_angle(value: float) -> float:
    """A float32 angle -> ``p·π/q`` (``q <= 1440``) if that rounds to it, else the decimal."""
    a32 = np.float32(value)
    if a32 == 0.0 or not math.isfinite(a32):
        return float(a32)
    frac = Fraction(float(a32) / math.pi).limit_denominator(_PI_DENOMINATOR)
    if frac.numerator != 0:
        cand = frac.numerator * math.pi / frac.denominator
        if np.float32(cand) == a32:
            return cand
    return float(widen_decimal(np.array([a32], dtype=np.float32))[0])


def _rotation() -> type[Rotation]:
    """scipy's ``Rotation``, imported on first use (scipy costs most of a cold start)."""
    from scipy.spatial.transform import Rotation

    return Rotation


def quaternion_yaw(x: float, y: float, z: float, w: float) -> float:
    """Heading (rad, ``[-π, π]``) of a quaternion: the first angle of its ZYX Euler angles."""
    return float(_rotation().from_quat([x, y, z, w]).as_euler("ZYX")[0])


def yaw_quaternion(yaw_rad: float) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` of a rotation about z whose :func:`quaternion_yaw` is exactly ``yaw_rad``.

    ``(0, 0, sin(yaw/2), cos(yaw/2))``, nudged by a few ulps where needed (any of them is the
    same rotation to 1e-16) so that written headings read back bit for bit.
    """
    z0, w0 = math.sin(yaw_rad / 2.0), math.cos(yaw_rad / 2.0)
    for k in range(9):
        for dz, dw in ((k, 0), (-k, 0), (0, k), (0, -k)):
            z = _ulps(z0, dz)
            w = _ulps(w0, dw)
            if quaternion_yaw(0.0, 0.0, z, w) == yaw_rad:
                return 0.0, 0.0, z, w
    return 0.0, 0.0, z0, w0


def _ulps(x: float, k: int) -> float:
    for _ in range(abs(k)):
        x = math.nextafter(x, math.inf if k > 0 else -math.inf)
    return x


def _se2_log(d: FloatArray) -> FloatArray:
    """``log`` of an SE(2) pose ``[x, y, theta]`` -> twist ``[v_x, v_y, omega]``."""
    th = float(d[2])
    if abs(th) < 1e-9:
        return np.array([d[0], d[1], th])
    a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th
    det = a * a + b * b
    return np.array([(a * d[0] + b * d[1]) / det, (-b * d[0] + a * d[1]) / det, th])


def _se2_exp(xi: FloatArray) -> FloatArray:
    th = float(xi[2])
    if abs(th) < 1e-9:
        return np.array([xi[0], xi[1], th])
    a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th
    return np.array([a * xi[0] - b * xi[1], b * xi[0] + a * xi[1], th])


def interpolate_se2(p0: FloatArray, p1: FloatArray, f: float) -> FloatArray:
    """Pose a fraction ``f`` in ``[0, 1]`` along the SE(2) geodesic from ``p0`` to ``p1``.

    Args:
        p0, p1: ``(3,)`` float64 poses ``[x_m, y_m, theta_rad]`` in the same frame.
        f: 0 gives ``p0`` exactly, 1 gives ``p1`` exactly.

    Returns:
        ``(3,)`` float64 ``p0 ∘ exp(f · log(p0⁻¹ ∘ p1))`` (Barfoot 2017, §7.1.7).
    """
    if f <= 0.0:
        return p0.copy()
    if f >= 1.0:
        return p1.copy()
    step = _se2_exp(f * _se2_log(se2.between(p0, p1)))
    out = se2.compose(p0, step)
    out[2] = float(se2.wrap_angle(out[2]))
    return out


# ---------------------------------------------------------------------------------------------
# tf: 3D transforms, a static frame tree, mounting projected to SE(2)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Transform3:
    """A rigid transform ``parent -> child``: translation (3,) m and rotation (scipy)."""

    t: FloatArray
    r: Rotation

    def compose(self, other: Transform3) -> Transform3:
        return Transform3(self.t + self.r.apply(other.t), self.r * other.r)

    def inverse(self) -> Transform3:
        inv = self.r.inv()
        return Transform3(-inv.apply(self.t), inv)


def _transform_of(msg: Any) -> Transform3:
    tr, q = msg.transform.translation, msg.transform.rotation
    return Transform3(np.array([tr.x, tr.y, tr.z]), _rotation().from_quat([q.x, q.y, q.z, q.w]))


def _frame(name: str) -> str:
    """ROS 1 frame ids may carry a leading slash; tf2 ignores it."""
    return name.lstrip("/")


def _in_tf(s: Survey, frame: str) -> bool:
    """Whether a transform of the bag (``/tf_static`` or ``/tf``) names ``frame``."""
    return any(frame in pair for pair in s.static_edges)


def _chain(edges: dict[tuple[str, str], Transform3], src: str, dst: str) -> Transform3 | None:
    """Transform ``src -> dst`` through the tree of ``edges`` (either direction), or None."""
    if src == dst:
        return Transform3(np.zeros(3), _rotation().identity())
    adj: dict[str, list[tuple[str, Transform3]]] = {}
    for (parent, child), tf in edges.items():
        adj.setdefault(parent, []).append((child, tf))
        adj.setdefault(child, []).append((parent, tf.inverse()))
    seen = {src: Transform3(np.zeros(3), _rotation().identity())}
    queue = deque([src])
    while queue:
        node = queue.popleft()
        for nxt, tf in adj.get(node, []):
            if nxt not in seen:
                seen[nxt] = seen[node].compose(tf)
                queue.append(nxt)
    return seen.get(dst)


@dataclass(frozen=True)
class Mounting:
    """The laser pose in the base frame, projected to SE(2).

    Attributes:
        offset: ``(3,)`` float64 ``[x_m, y_m, yaw_rad]`` of the laser in the base frame.
        flipped: The laser is upside down: its bearings are mirrored (``a -> -a``).
        tilt_rad: Angle between the laser's z axis and the base's (``π`` minus it if flipped).
    """

    offset: FloatArray
    flipped: bool = False
    tilt_rad: float = 0.0


def project_mounting(tf: Transform3, where: str, max_tilt_rad: float) -> Mounting:
    """Project a 3D laser mounting to SE(2); an upside-down laser is mirrored.

    Args:
        tf: base frame -> laser frame.
        where: Names the bag and frames for the error message.
        max_tilt_rad: Largest tilt of the scan plane from the base's x-y plane.

    Raises:
        LogFormatError: the scan plane is tilted more than ``max_tilt_rad``.
    """
    m = tf.r.as_matrix()
    z_up = float(m[2, 2])
    tilt = math.acos(min(1.0, abs(z_up)))
    if tilt > max_tilt_rad:
        raise LogFormatError(
            f"{where}: the laser is tilted {math.degrees(tilt):.1f} deg from the base's x-y plane "
            f"(at most {math.degrees(max_tilt_rad):.1f} deg is projected to 2D); a 2D SLAM needs a "
            "horizontal laser: pass --laser-frame-offset to override the mounting"
        )
    yaw = math.atan2(m[1, 0], m[0, 0])  # direction of the bearing-0 beam in the base frame
    return Mounting(np.array([tf.t[0], tf.t[1], yaw]), flipped=z_up < 0.0, tilt_rad=tilt)


# ---------------------------------------------------------------------------------------------
# Opening a bag
# ---------------------------------------------------------------------------------------------


def _rosbags() -> Any:
    try:
        import rosbags.highlevel
        import rosbags.typesys
    except ImportError as exc:
        raise LogFormatError(_INSTALL_HINT) from exc
    return rosbags


def is_bag(path: Path) -> bool:
    """True for a ``.bag`` / ``.db3`` / ``.mcap`` file or a folder holding ``metadata.yaml``."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix.lower() in (".bag", *_ROS2_SUFFIXES)


def _sniff(lines: list[str]) -> bool:
    """First line of a ROS 1 bag, an SQLite database or an MCAP file."""
    if not lines:
        return False
    head = lines[0]
    return head.startswith(("#ROSBAG V2", "SQLite format 3")) or "MCAP0" in head[:8]


def _is_ros1(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() == ".bag"


def _open_any(path: Path) -> Any:
    """An unopened ``AnyReader`` for ``path``: a ROS 1 bag defines its message types; a ROS 2
    bag that does not is read with the types of :func:`_read_types`."""
    rb = _rosbags()
    from rosbags.typesys import Stores, get_typestore

    if _is_ros1(path):
        return rb.highlevel.AnyReader([path])
    store = get_typestore(Stores.EMPTY)
    store.register(_read_types(ros1=False))
    return rb.highlevel.AnyReader([path], default_typestore=store)


@functools.cache
def _read_types(ros1: bool) -> dict[str, Any]:
    """The field definitions (rosbags' ``Typesdict``) of the message types this reader
    deserializes, the scans, odometry and tf (:data:`READ_TYPES`), and of the types they
    hold, from rosbags' Noetic or Humble typestore (those it has: Noetic's lacks tf2's), for a
    bag that does not define them. A reader's types are registered where it opens, and these
    15 take 0.02 s where the store's 150 took 0.2 s: the other topics are read from the
    bag's index only."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for msgtype in (t for t in READ_TYPES if t in store.fielddefs):
        # each definition's text holds those of the types it holds
        types.update(get_types_from_msg(store.generate_msgdef(msgtype)[0], msgtype))
    return types


_BAG_ERRORS: tuple[type[BaseException], ...] = (
    OSError,
    EOFError,
    ValueError,
    KeyError,
    IndexError,
    AssertionError,
)


def _bag_errors() -> tuple[type[BaseException], ...]:
    """Exceptions rosbags raises on a broken bag (its own, sqlite's, struct's, ...)."""
    import sqlite3
    import struct

    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error
    from rosbags.serde import SerdeError
    from rosbags.typesys import TypesysError

    own = (AnyReaderError, Reader1Error, Reader2Error, SerdeError, TypesysError)
    return (*own, sqlite3.Error, struct.error, *_BAG_ERRORS)


class _Bag:
    """An open AnyReader that fills in message types the bag does not define."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.reader: Any = None
        _rosbags()  # says which extra to install when rosbags is missing
        self.errors = _bag_errors()

    def __enter__(self) -> _Bag:
        try:
            self.reader = _open_any(self.path)
            self.reader.open()
            self._complete_types()
        except self.errors as exc:
            raise LogFormatError(f"{self.path}: cannot read the bag ({_why(exc)})") from exc
        return self

    def __exit__(self, *exc: object) -> None:
        if self.reader is not None and self.reader.stack is not None:
            self.reader.close()

    def _complete_types(self) -> None:
        """Register the read types (:func:`_read_types`) where the bag uses a type it does
        not define (some ROS 2 bags define a few)."""
        have = self.reader.typestore.fielddefs
        if not {c.msgtype for c in self.reader.connections} - set(have):
            return
        add = {k: v for k, v in _read_types(_is_ros1(self.path)).items() if k not in have}
        if add:
            self.reader.typestore.register(add)

    @property
    def connections(self) -> list[Any]:
        return list(self.reader.connections)

    def messages(self, connections: Sequence[Any], what: str) -> Iterator[tuple[Any, int, Any]]:
        """``(connection, receive_time_ns, message)`` in bag order; errors name the bag."""
        it = iter(self.reader.messages(connections=connections))
        while True:
            try:
                item = next(it, None)
                if item is None:
                    return
                conn, t_ns, raw = item
                msg = self.reader.deserialize(raw, conn.msgtype)
            except self.errors as exc:
                raise LogFormatError(
                    f"{self.path}: cannot read {what} ({_why(exc)}); is the bag truncated?"
                ) from exc
            yield conn, t_ns, msg


def _why(exc: BaseException) -> str:
    text = " ".join(str(exc).split())[:200]
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


# ---------------------------------------------------------------------------------------------
# The survey pass: topics, frames, tf tree
# ---------------------------------------------------------------------------------------------


@dataclass
class Survey:
    """What a bag holds, from its connections, ``/tf_static`` and ``/tf`` (one pass).

    Attributes:
        topics: ``{topic: (msgtype, message count)}``.
        storage: ``"ROS 1 bag"``, ``"ROS 2 sqlite3"`` or ``"ROS 2 mcap"``.
        duration_s: Receive-time span of the bag.
        static_edges: First transform of every ``(parent, child)`` frame pair seen (static
            first, then dynamic).
        dynamic_counts: ``{(parent, child): messages on /tf}``.
    """

    topics: dict[str, tuple[str, int]] = field(default_factory=dict)
    storage: str = ""
    duration_s: float = 0.0
    static_edges: dict[tuple[str, str], Transform3] = field(default_factory=dict)
    dynamic_counts: Counter[tuple[str, str]] = field(default_factory=Counter)

    def topics_of(self, msgtypes: Iterable[str]) -> list[str]:
        wanted = set(msgtypes)
        return sorted(t for t, (typ, _) in self.topics.items() if typ in wanted)


def _storage_name(path: Path) -> str:
    if _is_ros1(path):
        return "ROS 1 bag"
    files = [path] if path.is_file() else [*path.glob("*.mcap"), *path.glob("*.db3")]
    return "ROS 2 mcap" if any(f.suffix.lower() == ".mcap" for f in files) else "ROS 2 sqlite3"


def survey(bag: _Bag) -> Survey:
    """Topics and the tf tree of an open bag (reads only ``/tf`` and ``/tf_static``)."""
    s = Survey(storage=_storage_name(bag.path))
    counts: Counter[str] = Counter()
    for c in bag.connections:
        counts[c.topic] += c.msgcount
        s.topics[c.topic] = (c.msgtype, counts[c.topic])
    r = bag.reader
    s.duration_s = (r.end_time - r.start_time) / 1e9 if bag.connections else 0.0
    tf_conns = [c for c in bag.connections if c.topic in TF_TOPICS and c.msgtype == TF_TYPE]
    # Static transforms first, so a frame pair in both wins its /tf_static value.
    for topic in ("/tf_static", "/tf"):
        conns = [c for c in tf_conns if c.topic == topic]
        for _, _, msg in bag.messages(conns, f"{topic} messages") if conns else ():
            for tr in msg.transforms:
                key = (_frame(tr.header.frame_id), _frame(tr.child_frame_id))
                if key not in s.static_edges:  # the first of each pair is kept
                    s.static_edges[key] = _transform_of(tr)
                if topic == "/tf":
                    s.dynamic_counts[key] += 1
    return s


# ---------------------------------------------------------------------------------------------
# The reader
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class OdomSource:
    """Where odometry comes from: an Odometry topic, a /tf frame pair, or nothing."""

    kind: Literal["topic", "tf", "none"]
    topic: str | None = None
    odom_frame: str | None = None
    child_frame: str | None = None  # tf: the dynamic child of odom_frame

    def describe(self) -> str:
        if self.kind == "topic":
            return f"nav_msgs/Odometry on {self.topic}"
        if self.kind == "tf":
            return f"/tf {self.odom_frame} -> {self.child_frame}"
        return "none (laser only)"


@dataclass
class _Plan:
    scan_topic: str
    scan_type: str
    odom: OdomSource
    base_frame: str | None
    laser_frame: str
    child_to_base: Transform3 | None  # tf odometry: the base pose in the odom child frame
    mounting: Mounting


@register_reader("rosbag", (".bag", ".db3", ".mcap"), _sniff, sniff_dir=is_bag)
class RosbagReader:
    """Stream :class:`~frontends.scan.LaserScan` records from a ROS 1 or ROS 2 bag.

    See the module docstring for the conventions. Topic choice: the only LaserScan (or
    MultiEchoLaserScan, first echo) topic, else ``scan_topic``; odometry from the only
    ``nav_msgs/Odometry`` topic holding messages, else ``odom_topic``, else (no such topic)
    the ``/tf`` pair ``odom_frame -> *`` (default odom frame ``"odom"``); with none, scans have
    no odometry. The base frame is the Odometry's ``child_frame_id`` (or the tf child) unless
    ``base_frame`` is given; with no odometry and no tf naming the laser frame, the laser
    frame itself.

    Args:
        path: ``.bag``, ``.db3``, ``.mcap`` file, or a ROS 2 bag folder.
        scan_topic, odom_topic: Topics to use (needed when several candidates exist).
        odom_frame: Odometry from ``/tf``: the odom frame (its child there is the base).
        base_frame: The robot base frame: the mounting is the tf chain from it to the scan's
            frame_id (pass the laser frame itself for a laser-only bag without tf).
        laser_frame_offset: ``(3,)`` ``[x_m, y_m, yaw_rad]`` of the laser in the base frame,
            overriding tf.
        max_laser_tilt_rad: Largest laser tilt projected to 2D (see :func:`project_mounting`).
        max_pending_scans: Scans that may wait for a later odometry message (bounds memory).
        outside_odometry: A scan outside the odometry's time span gets ``odom_pose=None``
            (``"none"``, the default: the SLAM predicts it by constant velocity and starts
            the odometry frame anew at the first scan that has one) or is left out
            (``"drop"``).
        stamps: Header stamps out of order: ``"sort"`` reorders the scans through a buffer of
            ``max_reorder_scans`` (counted in :attr:`stamp_report`), ``"refuse"`` raises at the
            first stamp not after the previous one (as the CARMEN reader does).
        max_reorder_scans: How far (in scans) a scan may be out of place under ``"sort"``.

    Attributes:
        path: The bag.
        scans_without_odometry: Scans of the last iteration outside the odometry's time span.

    Raises:
        ConfigError: an option is invalid. Opening checks nothing else; iteration and
            :meth:`count_scans` raise ``LogFormatError`` for a bag that cannot be used.
    """

    def __init__(
        self,
        path: str | Path,
        scan_topic: str | None = None,
        odom_topic: str | None = None,
        odom_frame: str | None = None,
        base_frame: str | None = None,
        laser_frame_offset: Sequence[float] | None = None,
        max_laser_tilt_rad: float = MAX_LASER_TILT_RAD,
        max_pending_scans: int = 10_000,
        outside_odometry: Literal["none", "drop"] = "none",
        stamps: StampPolicy = "sort",
        max_reorder_scans: int = 1000,
    ) -> None:
        self.path = Path(path)
        self.scan_topic = scan_topic
        self.odom_topic = odom_topic
        self.odom_frame = _frame(odom_frame) if odom_frame else None
        self.base_frame = _frame(base_frame) if base_frame else None
        self.laser_frame_offset = _offset_option(laser_frame_offset)
        if not 0.0 <= max_laser_tilt_rad < math.pi / 2 or max_pending_scans < 1:
            raise ConfigError(
                f"RosbagReader: max_laser_tilt_rad {max_laser_tilt_rad} must be in [0, pi/2) "
                f"and max_pending_scans {max_pending_scans} >= 1"
            )
        if outside_odometry not in ("none", "drop"):
            raise ConfigError(f"outside_odometry {outside_odometry!r}: use 'none' or 'drop'")
        self.outside_odometry = outside_odometry
        self.max_laser_tilt_rad = max_laser_tilt_rad
        self.max_pending_scans = max_pending_scans
        self.scans_without_odometry = 0
        if stamps not in ("sort", "refuse") or max_reorder_scans < 1:
            raise ConfigError(
                f"RosbagReader: stamps {stamps!r} must be 'sort' or 'refuse' and "
                f"max_reorder_scans {max_reorder_scans} >= 1"
            )
        self.stamp_report = StampReport(policy=stamps)
        self.max_reorder_scans = max_reorder_scans

    def __repr__(self) -> str:
        return f"RosbagReader({str(self.path)!r}, scan_topic={self.scan_topic!r})"

    # -- public ----------------------------------------------------------------------------

    def count_scans(self) -> int:
        """Messages on the scan topic (from the bag's index; no message is read)."""
        with _Bag(self.path) as bag:
            topic, _ = self._scan_topic(survey_topics(bag))
            return sum(c.msgcount for c in bag.connections if c.topic == topic)

    def describe(self) -> list[tuple[str, str]]:
        """``(key, value)`` rows for ``iceg info``: storage, topics, tf frame pairs, then the
        reading plan (topics, frames, mounting) and the first scan; where the plan needs an
        option, the last row says which instead.

        Raises:
            LogFormatError: the bag cannot be read.
        """
        with _Bag(self.path) as bag:
            s = survey(bag)
            rows = [("format", s.storage), ("duration", f"{s.duration_s:.1f} s")]
            rows += [(t, f"{typ} × {n}") for t, (typ, n) in sorted(s.topics.items())]
            dynamic = _listing(f"{p} -> {c}" for p, c in sorted(s.dynamic_counts))
            rows.append(("tf", f"{len(s.static_edges)} frame pairs; changing on /tf: {dynamic}"))
            try:
                plan = self._plan(bag, s)
                first = next(self._scans(bag, plan, limit=1), None)
            except LogFormatError as exc:
                return [*rows, ("reading needs an option", str(exc).split(": ", 1)[-1])]
        return rows + _plan_rows(plan) + (_scan_rows(first) if first is not None else [])

    def __iter__(self) -> Iterator[LaserScan]:
        """Stream the scans in bag order, with odometry interpolated at their stamps.

        Raises:
            LogFormatError: unreadable or truncated bag, no or ambiguous scan topic, a topic
                of the wrong type, a laser frame tf does not link to the base frame.
        """
        self.scans_without_odometry = 0
        n = 0
        self.stamp_report = StampReport(policy=self.stamp_report.policy)
        with _Bag(self.path) as bag:
            plan = self._plan(bag, survey(bag))
            if plan.base_frame == plan.laser_frame and self.base_frame is None:
                logger.warning(
                    "%s: topic %s: no odometry, and no tf names laser frame %r: the trajectory "
                    "is the laser's (pass --base-frame or --laser-frame-offset X_M,Y_M,YAW_DEG "
                    "for the robot base's)",
                    self.path,
                    plan.scan_topic,
                    plan.laser_frame,
                )
            drop = self.outside_odometry == "drop" and plan.odom.kind != "none"
            tagged = ((None, scan) for scan in self._scans(bag, plan))
            for _, scan in order_by_stamp(tagged, self.stamp_report, self.max_reorder_scans):
                n += 1
                if scan.odom_pose is not None or not drop:
                    yield scan
        if self.scans_without_odometry:
            logger.warning(
                "%s: %d of %d scans lie outside the odometry's time span (%s): %s",
                self.path,
                self.scans_without_odometry,
                n,
                plan.odom.describe(),
                "left out" if self.outside_odometry == "drop" else "they have no odometry pose",
            )

    # -- planning --------------------------------------------------------------------------

    def _scan_topic(self, topics: dict[str, tuple[str, int]]) -> tuple[str, str]:
        cands = sorted(t for t, (typ, _) in topics.items() if typ in SCAN_TYPES)
        if self.scan_topic is not None:
            if self.scan_topic not in topics:
                raise LogFormatError(
                    f"{self.path}: no topic {self.scan_topic}; scan topics: {_listing(cands)}"
                )
            typ = topics[self.scan_topic][0]
            if typ not in SCAN_TYPES:
                raise LogFormatError(
                    f"{self.path}: topic {self.scan_topic} carries {typ}, not a laser scan "
                    f"(sensor_msgs/LaserScan or MultiEchoLaserScan); scan topics: {_listing(cands)}"
                )
            return self.scan_topic, typ
        if len(cands) != 1:
            what = "no laser scan topic" if not cands else f"{len(cands)} laser scan topics"
            raise LogFormatError(
                f"{self.path}: {what} (sensor_msgs/LaserScan); candidates: {_listing(cands)}; "
                "choose one with --scan-topic"
            )
        return cands[0], topics[cands[0]][0]

    def _odom_source(self, s: Survey) -> OdomSource:
        # A topic recorded without a message (its publisher never ran) is no odometry.
        odom_topics = [t for t in s.topics_of([ODOM_TYPE]) if s.topics[t][1] > 0]
        if self.odom_topic is not None:
            typ = s.topics.get(self.odom_topic, ("no such topic", 0))[0]
            if typ != ODOM_TYPE:
                raise LogFormatError(
                    f"{self.path}: odometry topic {self.odom_topic} carries {typ}, not "
                    f"nav_msgs/Odometry; Odometry topics: {_listing(odom_topics)}"
                )
            return OdomSource("topic", topic=self.odom_topic)
        if self.odom_frame is None and len(odom_topics) == 1:
            return OdomSource("topic", topic=odom_topics[0])
        if self.odom_frame is None and len(odom_topics) > 1:
            raise LogFormatError(
                f"{self.path}: {len(odom_topics)} odometry topics {_listing(odom_topics)}; "
                "choose one with --odom-topic (or --odom-frame for /tf)"
            )
        return self._tf_odom_source(s)

    def _tf_odom_source(self, s: Survey) -> OdomSource:
        frame = self.odom_frame or "odom"
        children = sorted(c for (p, c) in s.dynamic_counts if p == frame)
        if self.base_frame in children:
            children = [self.base_frame]
        if len(children) == 1:
            return OdomSource("tf", odom_frame=frame, child_frame=children[0])
        if self.odom_frame is None and not children:
            return OdomSource("none")
        pairs = _listing(f"{p} -> {c}" for (p, c) in sorted(s.dynamic_counts))
        raise LogFormatError(
            f"{self.path}: /tf has {len(children)} transforms from odom frame {frame!r} "
            f"(dynamic /tf pairs: {pairs}); pass --odom-frame and --base-frame"
        )

    def _plan(self, bag: _Bag, s: Survey) -> _Plan:
        topic, typ = self._scan_topic(s.topics)
        odom = self._odom_source(s)
        laser_frame = self._first_frame(bag, topic, "header.frame_id")
        base = self.base_frame
        if base is None and odom.kind == "topic":
            base = self._first_frame(bag, odom.topic or "", "child_frame_id")
        if base is None and odom.kind == "tf":
            base = odom.child_frame
        unmounted = self.laser_frame_offset is None and not _in_tf(s, laser_frame)
        if base is None and odom.kind == "none" and unmounted:
            # No odometry and nothing places the laser: its frame is the robot's only frame
            # (the trajectory is the laser's; a mounting option gives the base's).
            base = laser_frame
        child_to_base = None
        if odom.kind == "tf" and base is not None:
            child_to_base = _chain(s.static_edges, odom.child_frame or "", base)
            if child_to_base is None:
                raise LogFormatError(
                    f"{self.path}: tf links odometry frame {odom.child_frame} to no base frame "
                    f"{base!r}; pass --base-frame"
                )
        mount = self._mounting(s, base, laser_frame, topic)
        return _Plan(topic, typ, odom, base, laser_frame, child_to_base, mount)

    def _mounting(self, s: Survey, base: str | None, laser: str, topic: str) -> Mounting:
        if self.laser_frame_offset is not None:
            return Mounting(self.laser_frame_offset)
        hint = (
            "pass --base-frame (the frame tf links the laser to) or "
            "--laser-frame-offset X_M,Y_M,YAW_DEG"
        )
        if base is None:
            raise LogFormatError(
                f"{self.path}: topic {topic}: no odometry gives a base frame for laser frame "
                f"{laser!r}; {hint} (--base-frame {laser} for a laser-only run)"
            )
        tf = _chain(s.static_edges, base, laser)
        if tf is None:
            raise LogFormatError(
                f"{self.path}: topic {topic}: no tf (/tf_static or /tf) links base frame "
                f"{base!r} to laser frame {laser!r}; {hint}"
            )
        where = f"{self.path}: topic {topic}: {base} -> {laser}"
        return project_mounting(tf, where, self.max_laser_tilt_rad)

    def _first_frame(self, bag: _Bag, topic: str, attr: str) -> str:
        conns = [c for c in bag.connections if c.topic == topic]
        for _, _, msg in bag.messages(conns, f"topic {topic}"):
            value: Any = msg
            for part in attr.split("."):
                value = getattr(value, part)
            return _frame(str(value))
        raise LogFormatError(f"{self.path}: topic {topic} holds no messages")

    # -- streaming -------------------------------------------------------------------------

    def _scans(self, bag: _Bag, plan: _Plan, limit: int | None = None) -> Iterator[LaserScan]:
        """Scans in bag order; each waits until odometry at or after its stamp has arrived."""
        topics = {plan.scan_topic, *_odom_topics(plan.odom)}
        conns = [c for c in bag.connections if c.topic in topics]
        odom = _OdomBuffer()
        pending: deque[LaserScan] = deque()
        n = 0
        for conn, _, msg in bag.messages(conns, f"topics {', '.join(sorted(topics))}"):
            if conn.topic != plan.scan_topic:
                self._add_odom(odom, msg, plan)
            elif limit is not None and n >= limit:
                return
            else:
                pending.append(self._laser_scan(msg, plan, f"{self.path}:{conn.topic}#{n}"))
                n += 1
            wait = plan.odom.kind != "none" and limit is None
            while pending and not (wait and not odom.covers(pending[0].stamp_s)):
                yield self._with_odom(pending.popleft(), odom, plan)
            if len(pending) > self.max_pending_scans:
                raise LogFormatError(
                    f"{self.path}: {len(pending)} scans on {plan.scan_topic} wait for odometry "
                    f"({plan.odom.describe()}) at or after their stamps; raise max_pending_scans"
                )
        while pending:
            yield self._with_odom(pending.popleft(), odom, plan)

    def _with_odom(self, scan: LaserScan, odom: _OdomBuffer, plan: _Plan) -> LaserScan:
        if plan.odom.kind == "none":
            return scan
        pose = odom.at(scan.stamp_s)
        if pose is None:
            self.scans_without_odometry += 1
            return scan
        return _replace_odom(scan, pose)

    def _add_odom(self, odom: _OdomBuffer, msg: Any, plan: _Plan) -> None:
        if plan.odom.kind == "topic":
            p, q = msg.pose.pose.position, msg.pose.pose.orientation
            stamp = _stamp_s(msg.header.stamp.sec, msg.header.stamp.nanosec)
            odom.add(stamp, np.array([p.x, p.y, quaternion_yaw(q.x, q.y, q.z, q.w)]))
            return
        for tr in msg.transforms:
            if (_frame(tr.header.frame_id), _frame(tr.child_frame_id)) != (
                plan.odom.odom_frame,
                plan.odom.child_frame,
            ):
                continue
            tf = _transform_of(tr)
            if plan.child_to_base is not None:
                tf = tf.compose(plan.child_to_base)
            yaw = float(tf.r.as_euler("ZYX")[0])
            stamp = _stamp_s(tr.header.stamp.sec, tr.header.stamp.nanosec)
            odom.add(stamp, np.array([tf.t[0], tf.t[1], yaw]))

    def _laser_scan(self, msg: Any, plan: _Plan, source: str) -> LaserScan:
        if plan.scan_type == SCAN_TYPES[1]:
            ranges32 = np.array(
                [e.echoes[0] if len(e.echoes) else np.nan for e in msg.ranges], dtype=np.float32
            )
        else:
            ranges32 = np.asarray(msg.ranges, dtype=np.float32)
        key = (msg.angle_min, msg.angle_increment, ranges32.size, msg.range_min, msg.range_max)
        angles, rmin, rmax, reverse = _scan_geometry(*key, plan.mounting.flipped)
        ranges = widen_decimal(ranges32)
        with np.errstate(invalid="ignore"):
            ranges[~(np.isfinite(ranges) & (ranges >= rmin)) & ~(ranges >= rmax)] = np.inf
        if reverse:
            ranges = ranges[::-1].copy()
        return LaserScan(
            stamp_s=_stamp_s(msg.header.stamp.sec, msg.header.stamp.nanosec),
            ranges_m=ranges,
            angles_rad=angles,
            range_min_m=rmin,
            range_max_m=rmax,
            odom_pose=None,
            laser_offset=plan.mounting.offset,
            source=source,
        )


@functools.lru_cache(maxsize=64)
def _scan_geometry(
    angle_min: float, increment: float, n: int, range_min: float, range_max: float, flip: bool
) -> tuple[FloatArray, float, float, bool]:
    """Bearings (read-only, shared by the scans of a laser), range limits, and whether the
    beams are reversed so that bearings increase (a clockwise or upside-down laser)."""
    rmin = float(widen_decimal(np.array([range_min], dtype=np.float32))[0])
    rmax = float(widen_decimal(np.array([range_max], dtype=np.float32))[0])
    step = widen_angle(increment)
    angles = np.asarray(widen_angle(angle_min) + np.arange(n) * step, np.float64)
    if flip:
        angles = -angles
    reverse = bool(angles.size > 1 and angles[1] < angles[0])
    if reverse:
        angles = angles[::-1].copy()
    angles.flags.writeable = False
    return angles, rmin, rmax, reverse


def _odom_topics(source: OdomSource) -> tuple[str, ...]:
    if source.kind == "topic":
        return (source.topic or "",)
    return ("/tf",) if source.kind == "tf" else ()


def survey_topics(bag: _Bag) -> dict[str, tuple[str, int]]:
    """``{topic: (msgtype, count)}`` from the bag's index (no message is read)."""
    out: dict[str, tuple[str, int]] = {}
    for c in bag.connections:
        out[c.topic] = (c.msgtype, out.get(c.topic, ("", 0))[1] + c.msgcount)
    return out


class _OdomBuffer:
    """Recent odometry poses sorted by stamp, for interpolation at scan stamps."""

    def __init__(self) -> None:
        self.stamps: list[float] = []
        self.poses: list[FloatArray] = []
        self.first: float | None = None
        self.seen = False

    def add(self, stamp: float, pose: FloatArray) -> None:
        self.seen = True
        self.first = stamp if self.first is None else min(self.first, stamp)
        i = bisect.bisect_right(self.stamps, stamp)
        self.stamps.insert(i, stamp)
        self.poses.insert(i, pose)
        if len(self.stamps) > 2 * _ODOM_HISTORY:
            del self.stamps[:-_ODOM_HISTORY]
            del self.poses[:-_ODOM_HISTORY]

    def covers(self, t: float) -> bool:
        """An odometry message at or after ``t`` has arrived."""
        return bool(self.stamps) and self.stamps[-1] >= t

    def at(self, t: float) -> FloatArray | None:
        """SE(2)-interpolated pose at ``t``; None outside the span seen."""
        if not self.stamps or self.first is None or t < self.first or t > self.stamps[-1]:
            return None
        i = bisect.bisect_left(self.stamps, t)
        if self.stamps[i] == t:
            return self.poses[i].copy()
        if i == 0:
            return None  # older than the history kept (cannot happen for bag-ordered data)
        t0, t1 = self.stamps[i - 1], self.stamps[i]
        return interpolate_se2(self.poses[i - 1], self.poses[i], (t - t0) / (t1 - t0))


def _replace_odom(scan: LaserScan, pose: FloatArray) -> LaserScan:
    return LaserScan(
        stamp_s=scan.stamp_s,
        ranges_m=scan.ranges_m,
        angles_rad=scan.angles_rad,
        range_min_m=scan.range_min_m,
        range_max_m=scan.range_max_m,
        odom_pose=pose,
        laser_offset=scan.laser_offset,
        source=scan.source,
    )


def _offset_option(value: Sequence[float] | None) -> FloatArray | None:
    if value is None:
        return None
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise ConfigError(
            f"laser_frame_offset must be 3 finite numbers [x_m, y_m, yaw_rad], got {value!r}"
        )
    return arr


def _listing(items: Iterable[str]) -> str:
    items = list(items)
    return ", ".join(items) if items else "none"


def _plan_rows(plan: _Plan) -> list[tuple[str, str]]:
    off = plan.mounting.offset
    flip = ", upside down (bearings mirrored)" if plan.mounting.flipped else ""
    mount = f"x {off[0]:.3f} m, y {off[1]:.3f} m, yaw {math.degrees(off[2]):.1f} deg{flip}"
    return [
        ("scan topic", f"{plan.scan_topic} ({plan.scan_type})"),
        ("odometry", plan.odom.describe()),
        ("base frame", _base_row(plan)),
        ("laser frame", f"{plan.laser_frame}: {mount}"),
    ]


def _base_row(plan: _Plan) -> str:
    if plan.base_frame == plan.laser_frame and plan.odom.kind == "none":
        return f"{plan.base_frame} (the laser's own: no odometry, no other frame in tf)"
    return plan.base_frame or "-"


def _scan_rows(scan: LaserScan) -> list[tuple[str, str]]:
    a = np.degrees(scan.angles_rad)
    valid = scan.valid_mask()
    return [
        ("beams", f"{scan.n_beams}, {a[0]:.1f} to {a[-1]:.1f} deg (laser frame)"),
        ("range limits", f"{scan.range_min_m:g} to {scan.range_max_m:g} m"),
        ("valid beams (first scan)", f"{int(valid.sum())} of {scan.n_beams}"),
    ]


# ---------------------------------------------------------------------------------------------
# The writer
# ---------------------------------------------------------------------------------------------

BagFormat = Literal["ros1", "sqlite3", "mcap"]


def write_rosbag(
    path: str | Path,
    scans: Iterable[LaserScan],
    bag_format: BagFormat = "ros1",
    scan_topic: str = "/scan",
    odom_topic: str = "/odom",
    frames: tuple[str, str, str] = ("odom", "base_link", "laser"),
    odometry: Iterable[tuple[float, FloatArray]] | None = None,
    laser_mount: Transform3 | None = None,
) -> int:
    """Write scans as a bag that :class:`RosbagReader` reads back unchanged.

    Each scan becomes a ``sensor_msgs/LaserScan`` (float32 ranges; evenly spaced bearings)
    and, when it has one, a ``nav_msgs/Odometry`` with the same stamp; the first scan's
    ``laser_offset`` goes to ``/tf_static`` (base -> laser). Receive times are the stamps.
    Decimal ranges and π-based bearings read back bit for bit (see the module docstring).

    Args:
        path: ``.bag`` for ``"ros1"``; a new folder for ``"sqlite3"`` / ``"mcap"`` (ROS 2).
        scans: Scans in time order, all with the same laser offset.
        bag_format: ``"ros1"``, ``"sqlite3"`` or ``"mcap"``.
        scan_topic, odom_topic: Topic names.
        frames: ``(odom, base, laser)`` frame ids.
        odometry: ``(stamp_s, (3,) pose)`` pairs written as the Odometry messages instead of
            the scans' ``odom_pose`` (e.g. at other stamps than the scans).
        laser_mount: The 3D base -> laser transform written to ``/tf_static`` instead of the
            first scan's ``laser_offset`` (e.g. an upside-down or tilted laser).

    Returns:
        Number of scans written.

    Raises:
        LogFormatError: rosbags is missing, or the bag cannot be written (e.g. it exists).
        ScanError: a scan's bearings are not evenly spaced or its offset differs.
    """
    _rosbags()
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ros1 = bag_format == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1:
        tfdef = get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_TYPE)
        store.register(tfdef)
    errors: tuple[type[BaseException], ...] = (*_writer_errors(), OSError)
    try:
        with _writer(Path(path), bag_format) as w:
            extra = _Extras(odometry, laser_mount)
            return _write_all(w, store, scans, (scan_topic, odom_topic), frames, extra)
    except errors as exc:
        raise LogFormatError(f"{path}: cannot write the bag ({_why(exc)})") from exc


def _writer_errors() -> tuple[type[BaseException], ...]:
    from rosbags.rosbag1 import WriterError as W1
    from rosbags.rosbag2 import WriterError as W2

    return (W1, W2)


def _writer(path: Path, bag_format: BagFormat) -> Any:
    if bag_format == "ros1":
        from rosbags.rosbag1 import Writer as Writer1

        return Writer1(path)
    if bag_format not in ("sqlite3", "mcap"):
        raise ConfigError(f"bag_format {bag_format!r}: use 'ros1', 'sqlite3' or 'mcap'")
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    plugin = StoragePlugin.MCAP if bag_format == "mcap" else StoragePlugin.SQLITE3
    return Writer2(path, version=9, storage_plugin=plugin)


@dataclass(frozen=True)
class _Extras:
    odometry: Iterable[tuple[float, FloatArray]] | None
    laser_mount: Transform3 | None


def _write_all(
    w: Any,
    store: Any,
    scans: Iterable[LaserScan],
    topics: tuple[str, str],
    frames: tuple[str, str, str],
    extra: _Extras,
) -> int:
    ser = store.serialize_ros1 if hasattr(w, "chunk_threshold") else store.serialize_cdr
    scan_c = w.add_connection(topics[0], SCAN_TYPES[0], typestore=store)
    odom_c = w.add_connection(topics[1], ODOM_TYPE, typestore=store)
    offset: FloatArray | None = None
    n = 0
    for scan in scans:
        ns = stamp_ns(scan.stamp_s)
        if offset is None:
            offset = scan.laser_offset
            mount = extra.laser_mount or _planar(offset)
            tf_c = w.add_connection("/tf_static", TF_TYPE, typestore=store)
            tf = _tf_message(store, ns, frames[1], frames[2], mount)
            w.write(tf_c, ns, ser(tf, TF_TYPE))
        elif not np.array_equal(offset, scan.laser_offset):
            raise ScanError(f"{scan.source}: laser offset differs from the first scan's")
        w.write(scan_c, ns, ser(_scan_message(store, ns, frames[2], scan), SCAN_TYPES[0]))
        if scan.odom_pose is not None and extra.odometry is None:
            msg = _odom_message(store, ns, frames[0], frames[1], scan.odom_pose)
            w.write(odom_c, ns, ser(msg, ODOM_TYPE))
        n += 1
    for stamp, pose in extra.odometry or ():
        ns = stamp_ns(stamp)
        msg = _odom_message(store, ns, frames[0], frames[1], np.asarray(pose, np.float64))
        w.write(odom_c, ns, ser(msg, ODOM_TYPE))
    return n


def _planar(offset: FloatArray) -> Transform3:
    """An SE(2) laser offset ``[x, y, yaw]`` as a 3D transform."""
    quat = yaw_quaternion(float(offset[2]))
    return Transform3(np.array([offset[0], offset[1], 0.0]), _rotation().from_quat(quat))


def _header(store: Any, ns: int, frame: str) -> Any:
    time = store.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    hdr = store.types["std_msgs/msg/Header"]
    if "seq" in store.fielddefs["std_msgs/msg/Header"][1][0]:
        return hdr(seq=0, stamp=time, frame_id=frame)
    return hdr(stamp=time, frame_id=frame)


def _scan_message(store: Any, ns: int, frame: str, scan: LaserScan) -> Any:
    a = scan.angles_rad
    n = a.size
    inc = (a[-1] - a[0]) / (n - 1) if n > 1 else 0.0
    if n > 2 and not np.allclose(np.diff(a), inc, rtol=0.0, atol=1e-9):
        from iceg_common.errors import ScanError

        raise ScanError(f"{scan.source}: bearings are not evenly spaced; a LaserScan needs them")
    return store.types[SCAN_TYPES[0]](
        header=_header(store, ns, frame),
        angle_min=float(a[0]),
        angle_max=float(a[-1]),
        angle_increment=float(inc),
        time_increment=0.0,
        scan_time=0.0,
        range_min=float(scan.range_min_m),
        range_max=float(scan.range_max_m),
        ranges=scan.ranges_m.astype(np.float32),
        intensities=np.zeros(0, dtype=np.float32),
    )


def _pose_msgs(store: Any, pose: FloatArray, z: float = 0.0) -> tuple[Any, Any]:
    x, y, qz, qw = float(pose[0]), float(pose[1]), *yaw_quaternion(float(pose[2]))[2:]
    quat = store.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=qz, w=qw)
    return store.types["geometry_msgs/msg/Point"](x=x, y=y, z=z), quat


def _odom_message(store: Any, ns: int, parent: str, child: str, pose: FloatArray) -> Any:
    t = store.types
    point, quat = _pose_msgs(store, pose)
    cov = np.zeros(36, dtype=np.float64)
    return t[ODOM_TYPE](
        header=_header(store, ns, parent),
        child_frame_id=child,
        pose=t["geometry_msgs/msg/PoseWithCovariance"](
            pose=t["geometry_msgs/msg/Pose"](position=point, orientation=quat), covariance=cov
        ),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](
                linear=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            ),
            covariance=cov,
        ),
    )


def _tf_message(store: Any, ns: int, parent: str, child: str, mount: Transform3) -> Any:
    t = store.types
    x, y, z = (float(v) for v in mount.t)
    qx, qy, qz, qw = (float(v) for v in mount.r.as_quat())
    vec = t["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)
    quat = t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)
    stamped = t["geometry_msgs/msg/TransformStamped"](
        header=_header(store, ns, parent),
        child_frame_id=child,
        transform=t["geometry_msgs/msg/Transform"](translation=vec, rotation=quat),
    )
    return t[TF_TYPE](transforms=[stamped])
