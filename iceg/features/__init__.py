"""ICE features of a laser scan: segmentation, line fitting, Corner / EOW / Intersection.

Paper §III-B and §III-C1; docs/design.md "ICE matching, step by step", steps 1-4.
``extract(scan, config) -> ScanFeatures`` is the entry point.
"""

from iceg.features.config import FeatureConfig
from iceg.features.extract import extract, extract_points

__all__ = ["FeatureConfig", "extract", "extract_points"]
