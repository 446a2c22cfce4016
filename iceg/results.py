"""The result of a SLAM run: an object to inspect in a notebook and to save to a folder."""

from __future__ import annotations

import json
import shutil
import tempfile
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from frontends.tum import write_tum
from iceg.grid import OccupancyGrid, write_map_server, write_png
from iceg_common.atomic import atomic_write

if TYPE_CHECKING:
    from graph import FactorRecord, PoseGraph
    from iceg.config import IcegConfig
    from iceg.feature_map import FeatureMap
    from iceg.slam import LoopClosureStats

FloatArray = NDArray[np.float64]

#: Files :meth:`SlamResult.save` writes.
OUTPUT_FILES = (
    "trajectory.tum",
    "graph.g2o",
    "map.pgm",
    "map.yaml",
    "map.png",
    "metrics.json",
    "config.yaml",
)


@dataclass
class SlamResult:
    """Everything a run produced.

    Attributes:
        stamps_s: ``(N,)`` timestamp of every input scan, seconds.
        poses: ``(N, 3)`` optimized robot pose of every input scan ``[x_m, y_m, theta_rad]``
            in the map frame (non-node scans: their node's estimate ∘ odometry delta).
        node_ids: ``(M,)`` graph node ids; ``node_poses`` ``(M, 3)`` their estimates.
        node_scan_index: ``(M,)`` index of each node's scan in the input.
        factors: every factor of the graph (``graph.FactorRecord``: index, kind, nodes
            ``i``/``j``, measurement, covariance, robust kernel), the prior first.
        correlations: ICE correlation (eq. 1) of each scan-match and loop-closure factor,
            by factor index.
        loop_closures: loop-closure statistics.
        match_failures: count of failed local matches per reason.
        stage_seconds: wall time per pipeline stage, seconds.
        feature_map: the final feature map (landmarks anchored to nodes).
        grid: the occupancy grid rendered along ``poses`` (None for an empty run).
        graph: the pose graph (marginals, g2o export).
        config: the effective configuration.
        metrics: evaluation figures added by the caller (relations, ground truth).
    """

    stamps_s: FloatArray
    poses: FloatArray
    node_ids: NDArray[np.int64]
    node_poses: FloatArray
    node_scan_index: NDArray[np.int64]
    factors: tuple[FactorRecord, ...]
    correlations: dict[int, float]
    loop_closures: LoopClosureStats
    match_failures: dict[str, int]
    stage_seconds: dict[str, float]
    feature_map: FeatureMap
    grid: OccupancyGrid | None
    graph: PoseGraph
    config: IcegConfig
    metrics: dict[str, Any] = field(default_factory=dict)

    @property
    def n_scans(self) -> int:
        """Number of input scans."""
        return int(self.stamps_s.shape[0])

    def factor_counts(self) -> dict[str, int]:
        """Number of factors per kind."""
        return dict(Counter(f.kind.value for f in self.factors))

    def summary(self) -> dict[str, Any]:
        """Counts, timing and evaluation figures as a JSON-ready dict."""
        total = sum(self.stage_seconds.values())
        return {
            "scans": self.n_scans,
            "nodes": int(self.node_ids.shape[0]),
            "factors": self.factor_counts(),
            "loop_closures": self.loop_closures.as_dict(),
            "match_failures": self.match_failures,
            "stage_seconds": {k: round(v, 6) for k, v in self.stage_seconds.items()},
            "total_seconds": round(total, 6),
            "scans_per_second": self.n_scans / total if total > 0 else float("nan"),
            **self.metrics,
        }

    def __repr__(self) -> str:
        counts = self.factor_counts()
        lc = self.loop_closures
        parts = [
            f"scans={self.n_scans}",
            f"nodes={self.node_ids.shape[0]}",
            "factors={" + ", ".join(f"{k}: {v}" for k, v in sorted(counts.items())) + "}",
            f"loop_closures={lc.accepted}/{lc.attempts}",
            f"time={sum(self.stage_seconds.values()):.2f} s",
        ]
        rel = self.metrics.get("relations")
        if rel:
            parts.append(
                f"relation_error={rel['trans_mean_m']:.3f} m / {rel['rot_mean_deg']:.2f} deg"
            )
        gt = self.metrics.get("ground_truth")
        if gt:
            parts.append(f"position_error={gt['mean_m']:.3f} m")
        return "SlamResult(" + ", ".join(parts) + ")"

    def save(self, out_dir: str | Path) -> Path:
        """Write the result files (:data:`OUTPUT_FILES`) into ``out_dir``.

        Files are written in a staging folder beside ``out_dir`` and moved in only when all
        are complete, so an interrupted save leaves no partial file.

        Returns:
            ``out_dir`` as a Path.
        """
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
        try:
            write_tum(staging / "trajectory.tum", self.stamps_s, self.poses)
            self.graph.write_g2o(staging / "graph.g2o")
            if self.grid is not None:
                write_map_server(self.grid, staging / "map")
                write_png(self.grid, staging / "map.png", trajectory=self.poses)
            with atomic_write(staging / "metrics.json") as fh:
                json.dump(self.summary(), fh, indent=2, sort_keys=False)
                fh.write("\n")
            with atomic_write(staging / "config.yaml") as fh:
                fh.write(self.config.to_yaml())
            for f in sorted(staging.iterdir()):
                f.replace(out / f.name)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        return out
