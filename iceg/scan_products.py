"""A keyframe's pose-independent products, computed ahead beside its features (issue 13).

Besides the ICE features, each keyframe's processing derives quantities from the scan and its
features alone, never from the pose estimate: the matcher's feature geometry, polar profile,
point-to-segment index and the refinement's points on and off segments
(:func:`iceg.matching.matcher.scan_derived`), the feature map's
visibility geometry and beam profile (:func:`iceg.feature_map.visibility_inputs`) and the
place descriptor of the global loop-closure search
(:func:`iceg.place_index.place_descriptor`). :class:`ScanPrecompute` computes them in a
feature worker (:class:`~iceg.features.prefetch.FeaturePrefetcher`), right after the
features, and hands them to the modules that read them, which then serve them instead of
computing them again. A scan whose features were extracted in the calling process gets them
computed there when they are read, as before. They are the same functions on the same inputs
(the worker's copies of the scan and features are bit for bit the caller's), so the run is
the same bit for bit with or without workers (``tests/iceg/test_prefetch.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from frontends.scan import LaserScan
from iceg.config import IcegConfig
from iceg.feature_map import VisibilityInputs, remember_visibility_inputs, visibility_inputs
from iceg.kernel_warmup import compile_later_stages, compile_without_features
from iceg.matching.matcher import ScanDerived, compute_scan_derived, remember_scan_derived
from iceg.place_index import place_descriptor, remember_place_descriptor
from iceg.types import ScanFeatures


class ScanProducts(NamedTuple):
    """The pose-independent products of one keyframe (see the module docstring).

    Attributes:
        derived: The matcher's :class:`~iceg.matching.matcher.ScanDerived`.
        visibility: The feature map's :class:`~iceg.feature_map.VisibilityInputs`.
        place: ``(D,)`` float64 place descriptor, or None when the global loop-closure
            search is off (no descriptor is read).
    """

    derived: ScanDerived
    visibility: VisibilityInputs
    place: NDArray[np.float64] | None


@dataclass(frozen=True)
class ScanPrecompute:
    """Computes a scan's :class:`ScanProducts` (in a feature worker) and hands them to the
    modules that read them (in the calling process), for one run's configuration."""

    config: IcegConfig

    def compute(self, scan: LaserScan, features: ScanFeatures) -> ScanProducts:
        """The products of ``scan`` and its ``features``, as the pipeline's stages compute
        them."""
        lc = self.config.loop_closure
        place = (
            place_descriptor(features, lc.place_index) if lc.enabled and lc.global_search else None
        )
        return ScanProducts(
            compute_scan_derived(features),
            visibility_inputs(features, scan, self.config.feature_map.support_offset_m),
            place,
        )

    def warm_up_without_features(self, scan: LaserScan) -> None:
        """Compile the later stages' kernels that need no features, in the worker, on a new
        numba cache (:func:`iceg.kernel_warmup.compile_without_features`)."""
        compile_without_features(scan, self.config)

    def warm_up_with_features(self, scan: LaserScan, features: ScanFeatures) -> None:
        """Compile the later stages' kernels that need features, in the worker, on a new
        numba cache (:func:`iceg.kernel_warmup.compile_later_stages`)."""
        compile_later_stages(scan, features, self.config)

    def adopt(self, scan: LaserScan, features: ScanFeatures, products: ScanProducts) -> None:
        """Let the stages serve ``products`` (computed by :meth:`compute` for copies of
        ``scan`` and ``features``) for these objects."""
        remember_scan_derived(features, products.derived)
        remember_visibility_inputs(features, scan, products.visibility)
        if products.place is not None:
            remember_place_descriptor(
                features, self.config.loop_closure.place_index, products.place
            )
