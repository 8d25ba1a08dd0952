"""From an RGB-D frame to the rim cloud: colour segmentation, back-projection, extrinsics."""

import numpy as np
import pytest

from bagit.common.errors import BadCloud
from bagit.common.geometry import invert_transform, points_to_polyline_distance, transform_points
from bagit.common.messages import RgbdFrame
from bagit.common.rig import CameraConfig
from bagit.services.perception import extract_soi, red_rim_mask, rim_cloud
from bagit.services.perception.synthetic import true_rim


def render_rim_frame(rim: np.ndarray, cam: CameraConfig, band_m: float = 0.006) -> RgbdFrame:
    """A frame of a grey table 0.9 m below the rim and a red rim band drawn pixel by pixel with its depth."""
    info = cam.info()
    T_cw = invert_transform(info.extrinsics())
    h, w = info.height, info.width
    color = np.full((h, w, 3), 110, np.uint8)
    # Background: a plane (the table) at world z = 0, ray-intersected per pixel.
    v, u = np.mgrid[0:h, 0:w]
    rays = np.stack([(u - info.cx) / info.fx, (v - info.cy) / info.fy, np.ones_like(u, float)], axis=-1)
    R, t = info.extrinsics()[:3, :3], info.extrinsics()[:3, 3]
    dz = rays @ R[2]  # world z of a unit-depth ray
    depth = np.where(dz < 0, -t[2] / np.where(dz < 0, dz, -1), 0.0)
    # Rim band: dense samples across the band's width.
    offsets = np.linspace(-band_m / 2, band_m / 2, 5)
    pts = np.vstack([rim + [0, 0, o] for o in offsets])
    pc = transform_points(T_cw, pts)
    px = np.round(pc[:, 0] / pc[:, 2] * info.fx + info.cx).astype(int)
    py = np.round(pc[:, 1] / pc[:, 2] * info.fy + info.cy).astype(int)
    ok = (px >= 0) & (px < w) & (py >= 0) & (py < h)
    for x, y, z in zip(px[ok], py[ok], pc[ok, 2]):
        if depth[y, x] == 0 or z < depth[y, x] + 0.01:
            depth[y, x] = z
            color[y, x] = (200, 20, 25)
    depth_u16 = np.round(depth / info.depth_scale).astype(np.uint16)
    return RgbdFrame(camera=info, color=color, depth=depth_u16)


def test_red_rim_mask_and_back_projection_land_on_the_rim():
    cam = CameraConfig()
    rim = true_rim("ellipse", rpy=(0.1, 0.0, 0.3), center=(0.0, 0.0, 0.45), m=6000)
    frame = render_rim_frame(rim, cam)
    mask = red_rim_mask(frame)
    assert 300 < mask.sum() < 20000
    cloud = rim_cloud(frame)
    d = points_to_polyline_distance(cloud[::10], rim)
    assert np.median(d) < 0.004  # quantisation of depth (1 mm) and pixels (~2.5 mm at 1 m)
    soi = extract_soi(cloud, 32)
    assert points_to_polyline_distance(soi, rim).mean() < 0.004


def test_custom_segmenter_hook_and_depth_range():
    cam = CameraConfig()
    rim = true_rim("ellipse", center=(0.0, 0.0, 0.45), m=4000)
    frame = render_rim_frame(rim, cam)
    everything = rim_cloud(frame, segmenter=lambda f: f.depth > 0)
    assert len(everything) > len(rim_cloud(frame))
    assert len(rim_cloud(frame, depth_range=(5.0, 6.0))) == 0


def test_bad_segmenter_and_mismatched_images():
    cam = CameraConfig(width=64, height=48)
    frame = RgbdFrame(camera=cam.info(), color=np.zeros((48, 64, 3), np.uint8), depth=np.zeros((48, 64), np.uint16))
    with pytest.raises(BadCloud, match="mask"):
        rim_cloud(frame, segmenter=lambda f: np.zeros((3, 3), bool))
    bad = RgbdFrame(camera=cam.info(), color=np.zeros((10, 10, 3), np.uint8), depth=np.zeros((48, 64), np.uint16))
    with pytest.raises(BadCloud, match="differ"):
        rim_cloud(bad)
