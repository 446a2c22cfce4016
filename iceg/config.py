"""The whole configuration of a run: typed, validated, loadable from and writable to YAML.

Each module owns the model of its own parameters (``FeatureConfig`` in ``iceg.features``,
``MatchingConfig`` in ``iceg.matching``, ...); :class:`IcegConfig` composes them with the
pipeline's own :class:`SlamConfig` and the :class:`~iceg.loop_closure.LoopClosureConfig` of
:mod:`iceg.loop_closure` (re-exported here). ``iceg dump-config``
prints the defaults; every result folder holds the effective ``config.yaml``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from graph import GraphConfig, OdometryNoiseConfig
from iceg.feature_map import FeatureMapConfig
from iceg.features import FeatureConfig
from iceg.grid import GridConfig
from iceg.loop_closure import LoopClosureConfig
from iceg.matching import MatchingConfig
from iceg.odometry_calibration import OdometryCalibrationConfig
from iceg_common.errors import ConfigError


class SlamConfig(BaseModel):
    """Keyframing, local matching and offline refinement of the pipeline."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    keyframe_distance_m: float = Field(
        default=0.10,
        gt=0,
        description="A scan becomes a graph node after this odometry translation.",
    )
    keyframe_rotation_deg: float = Field(
        default=5.0, gt=0, description="... or after this odometry rotation."
    )
    keyframe_max_interval_s: float = Field(
        default=30.0, gt=0, description="... or after this time without a node (robot standing)."
    )
    local_map_nodes: int = Field(
        default=8, ge=1, description="Nodes whose landmarks form the local map for tracking."
    )
    match_max_translation_m: float = Field(
        default=0.5,
        gt=0,
        description="Admissible translation around the odometry prediction (§III-C2).",
    )
    match_max_rotation_deg: float = Field(
        default=20.0,
        gt=0,
        description="Admissible rotation around the odometry prediction (§III-C2).",
    )
    scan_match_kernel: Literal["huber", "cauchy"] | None = Field(
        default=None,
        description="M-estimator wrapped around scan-match factors, at its 95 %-efficiency "
        "width (Huber 1.345, Cauchy 2.3849 sigmas). A wrong match whose covariance leaves "
        "room (self-similar trees, a local map corrupted by one bad match) then ends many of "
        "its sigmas from the odometry and the rest of the graph, and the odometry carries "
        "that step. Off by default: on the outdoor world it cuts the ATE 2-4 times (huber, "
        "seeds 0-2: 1.19/0.96/1.67 -> 0.27/0.43/0.80 m) and it tightens MIT CSAIL's short "
        "relations, but there it costs the "
        "loop closures at the return to the start (0.037 -> 0.105 m; docs/design.md, "
        "'Robust scan-match factors').",
    )
    point_fallback: bool = Field(
        default=True,
        description="Where the ICE match against the local map has too little evidence (too "
        "few features, pairs or correlation; a degenerate scene: trees, posts, clutter) or "
        "the scan's points contradict it (contradiction_gate_m), match the scan's points "
        "against the recent nodes' points by point-to-line ICP seeded by the odometry (Censi "
        "2008) and keep it as the scan-match factor when it agrees with the odometry "
        "(chi-square test). With contradiction_gate_m (both are the defaults): every "
        "keyframe of the outdoor world gets a factor (ATE seeds 0-5: 0.061-0.107 m against "
        "0.44-3.39 m without either), MIT CSAIL with a 0.4 deg/m drift scores 0.030 m "
        "(0.047 m). The corrected logs with synthetic odometry, mean ATE over seeds 0-5: "
        "ACES 0.29 m (0.34 m without), csail.log 0.21 m (0.30 m), but csail-corrected "
        "0.16 m (0.13 m) (docs/design.md, 'Point fallback').",
    )
    contradiction_gate_m: float | None = Field(
        default=0.1,
        gt=0,
        description="When set, a successful ICE match against the local map is refused when "
        "the scan's points are explained (a recent node's point within this distance, "
        "metres) clearly better at the odometry prediction than at the match: a one-sided "
        "sign test at 0.999 on the points explained at one pose only "
        "(slam.points_prefer_prediction). It catches the look-alike clusters of trees and "
        "posts that turn a scan 5-20 degrees. 0.1 (the default) with point_fallback (a "
        "refused match then gets the point match): at 0.3 m points in clutter find a "
        "neighbour by chance and correct MIT CSAIL matches lost to odometry 4-7 degrees off; "
        "at 0.05 m the beams' spacing and noise count against correct matches. Without the "
        "fallback the refused steps are left to the odometry (MIT CSAIL 0.029 -> 0.045 m). "
        "None: no test (docs/design.md, 'Matches the points contradict').",
    )
    drop_walls_seen_through: bool = Field(
        default=True,
        description="Before a local match, drop the local map's walls that the last node's own "
        "scan sees through more than it confirms (a door that opened, a person who walked on), "
        "when that node was itself placed by a match. Otherwise a scan that sees past such a "
        "wall fails the free-space check at its true pose and the step is left to the "
        "odometry (docs/design.md, 'Walls that are gone').",
    )
    no_odometry_sigma_m: float = Field(
        default=0.5,
        gt=0,
        description="For logs without odometry: sigma of the constant-velocity "
        "motion prior between consecutive nodes, metres.",
    )
    no_odometry_sigma_deg: float = Field(
        default=20.0, gt=0, description="... and its rotation sigma, degrees."
    )
    batch_refinement: bool = Field(
        default=True,
        description="Run batch Levenberg–Marquardt over the whole graph after the run, with "
        "the accepted loop closures as Gaussian factors (no robust kernel).",
    )
    isam2_defer_from_nodes: int | None = Field(
        default=5000,
        ge=1,
        description="From this many nodes on, iSAM2 is updated once k * "
        "loop_closure.every_n_nodes keyframes wait, k the multiple of this the graph has "
        "reached, and after accepted loop closures; the keyframes in between take their "
        "estimate and covariance given the graph (PoseGraph.solve_pending). An iSAM2 update "
        "costs O(N) in gtsam 4.3 (docs/design.md, 'Long logs'). None: an update at every "
        "keyframe.",
    )
    reuse_nodes: bool = Field(
        default=True,
        description="Reduced pose graph (Johannsson et al., ICRA 2013): after a loop "
        "closure, the next keyframe is matched against the old place; while the match puts "
        "it within one keyframe spacing (keyframe_distance_m and keyframe_rotation_deg) of an "
        "old node, two standard deviations inside that spacing, the scans hang from that node "
        "and no node, factor or landmark is added. Where the path leaves the old nodes, a new "
        "node is linked to the last old one by the odometry and the match, as a keyframe to "
        "the node before it. The graph then grows with the area covered, not with the time "
        "spent in it: MIT CSAIL driven back and forth to 50k scans keeps 8.4k nodes instead "
        "of 45.6k, with the same relation error per pass; every benchmark case is unchanged "
        "or within its seed-to-seed noise (docs/design.md, 'Reused nodes'). False: a node "
        "per keyframe.",
    )
    workers: int = Field(
        default=0,
        ge=0,
        description="Processes of a whole run (iceg run): with 2 or more, ICE features of "
        "upcoming scans (and what the run derives from a scan alone) are computed in "
        "workers - 1 other processes while this one matches, and the loop-closure searches' "
        "matches run in one helper process while this one tracks; 0 picks 2 when a core is "
        "idle (auto_workers: the cores watched for 50 ms), else 1. The result is identical "
        "with any number (features do not depend on the pose, a match is a pure function of "
        "its inputs).",
    )

    def no_odometry_covariance(self) -> NDArray[np.float64]:
        """``(3, 3)`` float64 covariance of the constant-velocity motion prior between
        consecutive nodes where there is no odometry (``no_odometry_sigma_m``,
        ``no_odometry_sigma_deg``; m², rad²)."""
        sigma_rad = np.radians(self.no_odometry_sigma_deg)
        return np.diag([self.no_odometry_sigma_m**2] * 2 + [sigma_rad**2])


class IcegConfig(BaseModel):
    """Everything a run needs; each section is a module's own validated model."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    features: FeatureConfig = Field(default_factory=FeatureConfig)
    matching: MatchingConfig = Field(default_factory=MatchingConfig)
    feature_map: FeatureMapConfig = Field(default_factory=FeatureMapConfig)
    graph: GraphConfig = Field(default_factory=GraphConfig)
    odometry_noise: OdometryNoiseConfig = Field(default_factory=OdometryNoiseConfig)
    odometry_calibration: OdometryCalibrationConfig = Field(
        default_factory=OdometryCalibrationConfig
    )
    slam: SlamConfig = Field(default_factory=SlamConfig)
    loop_closure: LoopClosureConfig = Field(default_factory=LoopClosureConfig)
    grid: GridConfig = Field(default_factory=GridConfig)

    def to_yaml(self) -> str:
        """The configuration as YAML text (round-trips through :func:`config_from_yaml`)."""
        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False)


def config_from_dict(data: dict[str, Any], source: str = "<dict>") -> IcegConfig:
    """Validate a (partial) configuration dict; missing values take their defaults.

    Raises:
        ConfigError: an unknown key or an invalid value (including any non-finite float,
            e.g. ``.inf``), naming its path and the source.
    """
    try:
        config = IcegConfig.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise ConfigError(
            f"{source}: invalid config value at '{where}': {first['msg']}"
            + (f" ({len(exc.errors()) - 1} more)" if len(exc.errors()) > 1 else "")
        ) from exc
    for where, value in _floats(config.model_dump()):
        if not math.isfinite(value):
            raise ConfigError(
                f"{source}: invalid config value at '{where}': {value} is not a finite number"
            )
    return config


def _floats(tree: Any, prefix: str = "") -> list[tuple[str, float]]:
    """Every float of a nested dict/list, with its dotted path."""
    if isinstance(tree, float):
        return [(prefix, tree)]
    if isinstance(tree, dict):
        items = [(f"{prefix}.{k}" if prefix else str(k), v) for k, v in tree.items()]
    elif isinstance(tree, list | tuple):
        items = [(f"{prefix}.{i}", v) for i, v in enumerate(tree)]
    else:
        return []
    return [pair for key, value in items for pair in _floats(value, key)]


def config_from_yaml(path: str | Path) -> IcegConfig:
    """Load a configuration from a YAML file (partial files are filled with defaults).

    Raises:
        ConfigError: a missing or unparsable file, or an invalid value.
    """
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{p}: no such config file")
    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8")) or {}
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not a UTF-8 text file (byte {exc.start})") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read the config ({exc})") from exc
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{p}:{mark.line + 1}" if mark is not None else str(p)
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{where}: not valid YAML ({problem})") from exc
    if not isinstance(data, dict):
        raise ConfigError(
            f"{p}: the config must be a mapping of sections, got {type(data).__name__}"
        )
    return config_from_dict(data, source=str(p))
