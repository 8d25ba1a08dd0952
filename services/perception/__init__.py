"""Perception: RGB-D frames -> the bag-rim point cloud -> the rim as n_x ordered points (the SOI)."""

from bagit.services.perception.io import load_cloud
from bagit.services.perception.rgbd import back_project, red_rim_mask, rim_cloud
from bagit.services.perception.soi import extract_soi

__all__ = ["extract_soi", "rim_cloud", "back_project", "red_rim_mask", "load_cloud"]
