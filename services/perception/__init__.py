"""Perception: RGB-D frames -> the bag-rim point cloud -> the rim as n_x ordered points (the SOI)."""

from bagit.services.perception.io import load_cloud
from bagit.services.perception.rgbd import (
    Segmenter,
    back_project,
    hsv_segmenter,
    red_rim_mask,
    rim_cloud,
    solid_rim_segmenter,
)
from bagit.services.perception.soi import SoiParams, extract_soi

__all__ = [
    "extract_soi",
    "SoiParams",
    "rim_cloud",
    "back_project",
    "red_rim_mask",
    "hsv_segmenter",
    "solid_rim_segmenter",
    "Segmenter",
    "load_cloud",
]
