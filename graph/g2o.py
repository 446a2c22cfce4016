"""g2o files: read through ``gtsam.readG2o``, write at full precision.

Reading goes through ``gtsam.readG2o(path, is3D=False)``, with a text pass beside it that
counts the records: gtsam silently stops reading edges at the first line it does not know (a
comment, ``FIX``, a landmark), so a file with such a line in the middle would lose factors
without a word. That case is an error here.

Writing does not use ``gtsam.writeG2o``: it prints 6 significant digits (a pose 123.456789 m
from the origin comes back as 123.457) and refuses robust noise models. :func:`write_g2o_file`
writes the same ``VERTEX_SE2`` / ``EDGE_SE2`` records with ``repr`` floats (exact round trip)
and appends what g2o cannot say (factor kind, robust kernel, priors) as ``# ICEG_*`` comment
lines after the last record, where gtsam and g2o both skip them.

Record layout (g2o, Kümmerle et al. 2011): ``VERTEX_SE2 id x y theta`` and
``EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22 I23 I33`` with the upper triangle of the
information matrix (inverse covariance) in the tangent space of the measurement.
"""

from __future__ import annotations

import codecs
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import gtsam
import numpy as np
from numpy.typing import NDArray

from iceg_common.atomic import atomic_write
from iceg_common.errors import GraphError
from iceg_common.text import read_text_lines

FloatArray = NDArray[np.float64]

_SUPPORTED = ("VERTEX_SE2", "EDGE_SE2")
_UPPER = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


@dataclass(frozen=True)
class G2oPrior:
    """A prior written by :func:`write_g2o_file` (``# ICEG_PRIOR`` line).

    Attributes:
        node: node id.
        pose: ``(3,)`` ``[x_m, y_m, theta_rad]``, world frame.
        cov: ``(3, 3)`` covariance in the tangent space of the pose (body frame), (x, y, theta).
    """

    node: int
    pose: NDArray[np.float64]
    cov: NDArray[np.float64]


@dataclass(frozen=True)
class G2oGraph:
    """The content of a 2D g2o file as plain arrays (the raw edge list).

    Attributes:
        path: the file read.
        node_ids: ``(N,)`` int64, ascending.
        poses: ``(N, 3)`` float64 ``[x_m, y_m, theta_rad]`` of the ``VERTEX_SE2`` records,
            world frame, in the order of ``node_ids``.
        edge_ij: ``(M, 2)`` int64 node pairs ``(i, j)`` in file order.
        edge_measured: ``(M, 3)`` float64 ``pose_i^-1 ∘ pose_j``.
        edge_cov: ``(M, 3, 3)`` float64 covariances, inverse of the file's information matrices,
            in the tangent space of the measurement, ``(x, y, theta)`` order.
        edge_kind: ``M`` factor kinds (``"odometry"``, ``"scan_match"``, ``"loop_closure"``):
            from ``# ICEG_EDGE`` lines when present; otherwise ``"odometry"`` for ``j == i + 1``
            and ``"loop_closure"`` for every other edge (the convention of the public datasets).
        edge_robust: ``M`` robust kernels (``None``, ``"huber"``, ``"cauchy"``).
        edge_robust_k: ``(M,)`` kernel parameters (NaN where there is no kernel).
        priors: priors from ``# ICEG_PRIOR`` lines (empty for a foreign file).
        factor_order: ``("prior", p)`` / ``("edge", m)`` in the order the writer's graph held
            its factors; edges in file order for a foreign file.
    """

    path: Path
    node_ids: NDArray[np.int64]
    poses: NDArray[np.float64]
    edge_ij: NDArray[np.int64]
    edge_measured: NDArray[np.float64]
    edge_cov: NDArray[np.float64]
    edge_kind: tuple[str, ...]
    edge_robust: tuple[str | None, ...]
    edge_robust_k: NDArray[np.float64]
    priors: tuple[G2oPrior, ...]
    factor_order: tuple[tuple[str, int], ...]

    @property
    def n_edges(self) -> int:
        """Number of ``EDGE_SE2`` records."""
        return int(self.edge_ij.shape[0])


def _floats(values: Iterable[float] | NDArray[np.float64]) -> str:
    """The numbers as g2o writes them: shortest round-trip ``repr``, space-separated."""
    seq = values.tolist() if isinstance(values, np.ndarray) else [float(v) for v in values]
    return " ".join(map(repr, seq))


def _information(cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """Information matrices ``inv(cov)`` made symmetric, of one ``(3, 3)`` covariance or a
    stack ``(F, 3, 3)`` (one LAPACK solve per matrix either way)."""
    info = np.asarray(np.linalg.inv(cov), dtype=np.float64)
    return 0.5 * (info + np.swapaxes(info, -1, -2))


def _covariance_of(noise_model: Any) -> NDArray[np.float64]:  # a gtsam noise model
    model: Any = noise_model
    if isinstance(noise_model, gtsam.noiseModel.Robust):
        model = noise_model.noise()
    cov = np.linalg.inv(np.array(model.information(), dtype=np.float64))
    return 0.5 * (cov + cov.T)


def _scan(path: Path) -> tuple[int, int, list[tuple[int, list[str]]]]:
    """Count records and collect ``# ICEG_*`` lines; reject lines gtsam would stop at."""
    n_vertex = n_edge = 0
    iceg: list[tuple[int, list[str]]] = []
    last_record = 0
    first_comment = 0
    with open(path, "rb") as fh:
        if fh.read(len(codecs.BOM_UTF8)) == codecs.BOM_UTF8:
            raise GraphError(
                f"{path}:1: the file starts with a UTF-8 byte order mark, which gtsam.readG2o "
                "reads as part of the first record (it loses that record's pose); save the "
                "file without it"
            )
    lines = read_text_lines(path, "g2o file", GraphError)
    for line_no, line in enumerate(lines, start=1):
        tokens = line.split()
        if not tokens:
            continue
        if tokens[0].startswith("#"):
            first_comment = first_comment or line_no
            if len(tokens) > 1 and tokens[1].startswith("ICEG_"):
                iceg.append((line_no, tokens[1:]))
            continue
        if tokens[0] not in _SUPPORTED:
            raise GraphError(
                f"{path}:{line_no}: record {tokens[0]!r} is not supported: 2D g2o files may "
                f"hold only {' and '.join(_SUPPORTED)} records (gtsam.readG2o would silently "
                "drop the edges after it)"
            )
        n_vertex += tokens[0] == "VERTEX_SE2"
        n_edge += tokens[0] == "EDGE_SE2"
        last_record = line_no
    if first_comment and first_comment < last_record:
        raise GraphError(
            f"{path}:{first_comment}: comment line before the last record (line {last_record}): "
            "gtsam.readG2o stops reading edges at it; move comments to the end of the file"
        )
    return n_vertex, n_edge, iceg


def load_g2o(path: str | os.PathLike[str]) -> G2oGraph:
    """Read a 2D g2o file into arrays through ``gtsam.readG2o(path, is3D=False)``.

    Args:
        path: a g2o file of ``VERTEX_SE2`` and ``EDGE_SE2`` records, optionally followed by the
            ``# ICEG_*`` lines of :func:`write_g2o_file`.

    Returns:
        The raw vertices and edges (see :class:`G2oGraph`).

    Raises:
        GraphError: the file is missing, holds another record type or a comment before the
            last record, gtsam cannot parse it, or gtsam read fewer records than the file holds.
    """
    file = Path(path)
    if not file.is_file():
        raise GraphError(f"{file}: no such g2o file")
    n_vertex, n_edge, iceg = _scan(file)
    try:
        factors, values = gtsam.readG2o(str(file), False)
    except (RuntimeError, ValueError, IndexError) as exc:
        raise GraphError(f"{file}: gtsam.readG2o failed: {exc}") from exc
    if factors.size() != n_edge or values.size() != n_vertex:
        raise GraphError(
            f"{file}: gtsam.readG2o read {values.size()} vertices and {factors.size()} edges "
            f"but the file holds {n_vertex} VERTEX_SE2 and {n_edge} EDGE_SE2 records "
            "(duplicate vertex ids or malformed lines?)"
        )
    node_ids = np.asarray(list(values.keys()), dtype=np.int64)
    poses = (
        np.asarray(gtsam.utilities.extractPose2(values), dtype=np.float64).reshape(-1, 3)
        if n_vertex
        else np.zeros((0, 3))
    )
    edge_ij, measured, cov = _edges(factors)
    kinds = ["odometry" if j == i + 1 else "loop_closure" for i, j in edge_ij.tolist()]
    robust: list[str | None] = [None] * n_edge
    robust_k = np.full(n_edge, np.nan)
    priors: list[G2oPrior] = []
    order: list[tuple[str, int]] = [("edge", m) for m in range(n_edge)]
    if iceg:
        order = _apply_iceg_lines(file, iceg, kinds, robust, robust_k, priors)
    return G2oGraph(
        path=file,
        node_ids=node_ids,
        poses=poses,
        edge_ij=edge_ij,
        edge_measured=measured,
        edge_cov=cov,
        edge_kind=tuple(kinds),
        edge_robust=tuple(robust),
        edge_robust_k=robust_k,
        priors=tuple(priors),
        factor_order=tuple(order),
    )


def _edges(factors: Any) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
    """``(E, 2)`` node ids, ``(E, 3)`` measurements and ``(E, 3, 3)`` covariances of the
    ``BetweenFactorPose2`` edges gtsam read (``gtsam.readG2o``, ``is3D=False``)."""
    n_edge = factors.size()
    edge_ij = np.zeros((n_edge, 2), dtype=np.int64)
    measured = np.zeros((n_edge, 3))
    cov = np.zeros((n_edge, 3, 3))
    for m in range(n_edge):
        factor: Any = factors.at(m)
        edge_ij[m] = factor.keys()
        pose = factor.measured()
        measured[m] = (pose.x(), pose.y(), pose.theta())
        cov[m] = _covariance_of(factor.noiseModel())
    return edge_ij, measured, cov


def _apply_iceg_lines(
    file: Path,
    iceg: list[tuple[int, list[str]]],
    kinds: list[str],
    robust: list[str | None],
    robust_k: FloatArray,
    priors: list[G2oPrior],
) -> list[tuple[str, int]]:
    """Apply the ``# ICEG_PRIOR`` / ``# ICEG_EDGE`` lines of :func:`write_g2o_file`: fill the
    edges' kinds and kernels (in place) and the priors; return the factors' original order.

    Raises:
        GraphError: ``file:line`` of a malformed line, or an ICEG_EDGE count that differs from
            the EDGE_SE2 count.
    """
    n_edge = len(kinds)
    order: list[tuple[str, int]] = []
    n_meta_edges = 0
    for line_no, tokens in iceg:
        try:
            if tokens[0] == "ICEG_PRIOR" and len(tokens) == 11:
                nums = np.array([float(t) for t in tokens[2:]])
                prior_cov = np.zeros((3, 3))
                prior_cov[_UPPER] = nums[3:]
                prior_cov = prior_cov + np.triu(prior_cov, 1).T
                order.append(("prior", len(priors)))
                priors.append(G2oPrior(int(tokens[1]), nums[:3], prior_cov))
            elif tokens[0] == "ICEG_EDGE" and len(tokens) == 4 and n_meta_edges < n_edge:
                kinds[n_meta_edges] = tokens[1]
                robust[n_meta_edges] = None if tokens[2] == "none" else tokens[2]
                robust_k[n_meta_edges] = float(tokens[3])
                order.append(("edge", n_meta_edges))
                n_meta_edges += 1
            else:
                raise ValueError("unexpected fields")
        except ValueError as exc:
            raise GraphError(
                f"{file}:{line_no}: malformed {tokens[0]} line ({exc}); expected "
                "'# ICEG_PRIOR node x y theta c11 c12 c13 c22 c23 c33' or "
                "'# ICEG_EDGE kind robust k', one ICEG_EDGE line per EDGE_SE2 record"
            ) from exc
    if n_meta_edges != n_edge:
        raise GraphError(
            f"{file}: {n_meta_edges} '# ICEG_EDGE' lines for {n_edge} EDGE_SE2 records"
        )
    return order


class _Factor(Protocol):
    """What :func:`write_g2o_file` needs of a factor (``graph.FactorRecord`` has it)."""

    @property
    def kind(self) -> object: ...
    @property
    def i(self) -> int: ...
    @property
    def j(self) -> int | None: ...
    @property
    def measured(self) -> NDArray[np.float64]: ...
    @property
    def cov(self) -> NDArray[np.float64]: ...
    @property
    def robust(self) -> str | None: ...
    @property
    def robust_k(self) -> float | None: ...


def write_g2o_file(
    path: str | os.PathLike[str],
    node_ids: NDArray[np.int64],
    poses: NDArray[np.float64],
    factors: Sequence[_Factor],
) -> None:
    """Write a pose graph as a 2D g2o file, atomically (temporary file, then ``os.replace``).

    Args:
        path: destination; its directory must exist.
        node_ids: ``(N,)`` node ids.
        poses: ``(N, 3)`` ``[x_m, y_m, theta_rad]`` world-frame poses, one per id.
        factors: records with ``kind, i, j, measured, cov, robust, robust_k``; a record with
            ``j is None`` is a prior (written as a ``# ICEG_PRIOR`` line), the others become
            ``EDGE_SE2`` records with the information matrix ``inv(cov)``.

    Raises:
        GraphError: the file cannot be written.
    """
    file = Path(path)
    lines = [f"VERTEX_SE2 {n} {_floats(p)}" for n, p in zip(node_ids.tolist(), poses, strict=True)]
    meta = []
    edges = [f for f in factors if f.j is not None]
    infos = iter(_information(np.array([f.cov for f in edges])) if edges else np.zeros((0, 3, 3)))
    for f in factors:
        if f.j is None:
            meta.append(f"# ICEG_PRIOR {f.i} {_floats(f.measured)} {_floats(f.cov[_UPPER])}")
            continue
        info = next(infos)
        lines.append(f"EDGE_SE2 {f.i} {f.j} {_floats(f.measured)} {_floats(info[_UPPER])}")
        k = float("nan") if f.robust_k is None else f.robust_k
        kind = getattr(f.kind, "value", f.kind)
        meta.append(f"# ICEG_EDGE {kind} {f.robust or 'none'} {k!r}")
    text = "\n".join([*lines, *meta]) + "\n"
    try:
        with atomic_write(file) as stream:
            stream.write(text)
    except OSError as exc:
        raise GraphError(f"{file}: cannot write the g2o file: {exc}") from exc
