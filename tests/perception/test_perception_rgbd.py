"""From an RGB-D frame to the rim cloud: colour segmentation, back-projection, extrinsics, the hook."""

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from bagit.common.errors import BadCloud
from bagit.common.geometry import invert_transform, points_to_polyline_distance, transform_points
from bagit.common.messages import CameraInfo, RgbdFrame
from bagit.common.rig import CameraConfig
from bagit.services.perception import back_project, extract_soi, hsv_segmenter, red_rim_mask, rim_cloud
from bagit.services.perception.synthetic import true_rim

RED = (200, 20, 25)


def render_rim_frame(
    rim: np.ndarray,
    cam: CameraConfig,
    band_m: float = 0.006,
    color: tuple[int, int, int] = RED,
    occluder: tuple[np.ndarray, float] | None = None,
    noise_m: float = 0.0,
    seed: int = 0,
) -> RgbdFrame:
    """A frame of a grey table at world z = 0 and a coloured rim band (z-buffered), depth in mm units.

    occluder: (centre (3,), radius) of a grey ball (a gripper) drawn in front of the rim.
    """
    info = cam.info()
    T_wc = info.extrinsics()
    T_cw = invert_transform(T_wc)
    h, w = info.height, info.width
    v, u = np.mgrid[0:h, 0:w]
    rays = np.stack([(u - info.cx) / info.fx, (v - info.cy) / info.fy, np.ones((h, w))], axis=-1)
    dz = rays @ T_wc[:3, :3][2]  # world z change per unit camera depth
    depth = np.where(dz < 0, -T_wc[2, 3] / np.where(dz < 0, dz, -1.0), 0.0)
    image = np.full((h, w, 3), 110, np.uint8)
    # the rim band, densely sampled across its width, z-buffered per pixel
    tangent = np.roll(rim, -1, axis=0) - np.roll(rim, 1, axis=0)
    side = np.cross(tangent, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    pts = np.vstack([rim + o * side for o in np.linspace(-band_m / 2, band_m / 2, 7)])
    pc = transform_points(T_cw, pts)
    px = np.round(pc[:, 0] / pc[:, 2] * info.fx + info.cx).astype(int)
    py = np.round(pc[:, 1] / pc[:, 2] * info.fy + info.cy).astype(int)
    ok = (px >= 0) & (px < w) & (py >= 0) & (py < h) & (pc[:, 2] > 0)
    px, py, z = px[ok], py[ok], pc[ok, 2]
    order = np.lexsort((z, py * w + px))  # nearest first within each pixel
    first = np.r_[True, np.diff((py * w + px)[order]) != 0]
    sel = order[first]
    nearer = z[sel] < depth[py[sel], px[sel]]
    depth[py[sel][nearer], px[sel][nearer]] = z[sel][nearer]
    image[py[sel][nearer], px[sel][nearer]] = color
    if occluder is not None:
        centre, radius = occluder
        cc = transform_points(T_cw, centre[None])[0]
        cu, cv_ = cc[0] / cc[2] * info.fx + info.cx, cc[1] / cc[2] * info.fy + info.cy
        r_px = radius / cc[2] * info.fx
        ball = (u - cu) ** 2 + (v - cv_) ** 2 <= r_px**2
        depth[ball] = cc[2] - radius
        image[ball] = (90, 90, 95)
    if noise_m > 0:
        depth = depth + np.random.default_rng(seed).normal(0.0, noise_m, depth.shape) * (depth > 0)
    depth_u16 = np.round(np.clip(depth, 0, None) / info.depth_scale).astype(np.uint16)
    return RgbdFrame(camera=info, color=image, depth=depth_u16)


def test_red_rim_mask_and_back_projection_land_on_the_rim():
    cam = CameraConfig()
    rim = true_rim("ellipse", rpy=(0.1, 0.0, 0.3), center=(0.0, 0.0, 0.45), m=6000)
    frame = render_rim_frame(rim, cam, noise_m=0.001)
    mask = red_rim_mask(frame)
    assert 300 < mask.sum() < 20_000
    cloud = rim_cloud(frame)
    assert len(cloud) == mask.sum()
    d = points_to_polyline_distance(cloud[::5], rim)
    assert np.median(d) < 0.004  # quantisation of depth (1 mm) and pixels (~2.5 mm at 1 m), 1 mm noise
    soi = extract_soi(cloud, 32)
    assert points_to_polyline_distance(soi, rim).mean() < 0.003


def test_a_gripper_hides_part_of_the_rim():
    cam = CameraConfig()
    rim = true_rim("lens", rpy=(0.0, 0.0, np.pi / 2), center=(0.0, 0.0, 0.45), m=6000)  # handles at +-y
    left = rim[np.argmin(rim[:, 1])]
    towards_camera = (np.asarray(cam.position) - left) / np.linalg.norm(np.asarray(cam.position) - left)
    frame = render_rim_frame(rim, cam, occluder=(left + 0.08 * towards_camera, 0.03))
    cloud = rim_cloud(frame)
    hidden = rim[np.linalg.norm(rim - left, axis=1) < 0.02]
    assert cKDTree(cloud).query(hidden)[0].min() > 0.005  # the handle's stretch is not seen
    soi = extract_soi(cloud, 32, start_hint=left)
    d = points_to_polyline_distance(soi, rim)
    assert d.mean() < 0.002 and d.max() < 0.008  # 11 % of the rim hidden, at the pinched handle
    assert np.linalg.norm(soi[0] - left) < 0.01  # point 0 at the left handle, bridged under the gripper


def test_red_wraps_round_hue_zero_and_other_colours_are_not_red():
    # OpenCV hue of each test colour, then the mask over one pixel of each
    colours = {
        "red": ((220, 20, 20), True),
        "red_blue_side": ((220, 20, 60), True),  # hue ~175
        "red_yellow_side": ((220, 50, 20), True),  # hue ~4
        "orange": ((230, 140, 20), False),
        "pink_pale": ((230, 180, 180), False),  # low saturation
        "dark_red": ((40, 5, 5), False),  # low value
        "green": ((20, 200, 20), False),
        "blue": ((20, 20, 200), False),
    }
    image = np.array([[c for c, _ in colours.values()]], dtype=np.uint8)
    hues = cv2.cvtColor(image, cv2.COLOR_RGB2HSV)[0, :, 0]
    assert hues[1] > 170 and hues[2] < 10  # the two sides of the wrap
    cam = CameraInfo(width=len(colours), height=1)
    frame = RgbdFrame(camera=cam, color=image, depth=np.full((1, len(colours)), 1000, np.uint16))
    got = red_rim_mask(frame)[0]
    assert got.tolist() == [want for _, want in colours.values()]


def test_back_projection_inverts_the_pinhole_projection():
    info = CameraInfo(width=64, height=48, fx=50.0, fy=55.0, cx=31.5, cy=23.0)
    depth = np.zeros((48, 64))
    depth[10, 20] = 1.25
    depth[40, 60] = 0.5
    depth[5, 5] = np.nan  # no measurement
    pts = back_project(depth, info)
    assert pts.shape == (2, 3)
    assert np.allclose(pts[0], [(20 - 31.5) * 1.25 / 50.0, (10 - 23.0) * 1.25 / 55.0, 1.25])
    K = info.K()
    uvw = pts @ K.T
    assert np.allclose(uvw[:, :2] / uvw[:, 2:], [[20, 10], [60, 40]])


def test_the_rim_cloud_is_the_whole_image_back_projection_bit_for_bit():
    # The cloud converts only the mask's depths; the numbers and their order must be those of the
    # whole image in metres, masked and range-limited (what the SOI and every published run saw).
    cam = CameraConfig()
    rng = np.random.default_rng(3)
    frame = render_rim_frame(true_rim("ellipse", center=(0.0, 0.0, 0.45), m=4000), cam)
    frame.depth[rng.random(frame.depth.shape) < 0.05] = 0  # holes
    frame.depth[rng.random(frame.depth.shape) < 0.05] = 100  # nearer than the range
    mask = red_rim_mask(frame)
    depth_m = frame.depth.astype(np.float64) * frame.camera.depth_scale
    want = transform_points(frame.camera.extrinsics(), back_project(depth_m, frame.camera, mask & (depth_m >= 0.2) & (depth_m <= 3.0)))
    got = rim_cloud(frame)
    assert len(got) > 300 and got.shape == want.shape and np.array_equal(got, want)


def test_world_cloud_does_not_depend_on_where_the_camera_is():
    rim = true_rim("ellipse", center=(0.0, 0.0, 0.45), m=6000)
    clouds = [
        rim_cloud(render_rim_frame(rim, CameraConfig(position=p, look_at=(0.0, 0.0, 0.45))))
        for p in [(0.55, 0.0, 1.25), (-0.3, 0.4, 1.1)]
    ]
    for cloud in clouds:
        assert len(cloud) > 300 and np.median(points_to_polyline_distance(cloud[::5], rim)) < 0.004


def test_custom_segmenter_hook_and_depth_range():
    cam = CameraConfig()
    rim = true_rim("ellipse", center=(0.0, 0.0, 0.45), m=4000)
    frame = render_rim_frame(rim, cam, color=(20, 30, 210))  # a blue-edged bag
    assert len(rim_cloud(frame)) == 0  # nothing red
    blue = rim_cloud(frame, segmenter=hsv_segmenter([(110, 130)]))
    assert len(blue) > 300 and np.median(points_to_polyline_distance(blue[::5], rim)) < 0.004
    everything = rim_cloud(frame, segmenter=lambda f: f.depth > 0)
    assert len(everything) > len(blue)
    as_uint8 = rim_cloud(frame, segmenter=lambda f: (f.depth > 0).astype(np.uint8) * 255)
    assert len(as_uint8) == len(everything)
    assert len(rim_cloud(frame, segmenter=lambda f: f.depth > 0, depth_range=(5.0, 6.0))) == 0
    assert rim_cloud(frame, depth_range=(5.0, 6.0)).shape == (0, 3)


def test_bad_frames_segmenters_and_ranges():
    cam = CameraConfig(width=64, height=48)
    good = RgbdFrame(camera=cam.info(), color=np.zeros((48, 64, 3), np.uint8), depth=np.zeros((48, 64), np.uint16))
    with pytest.raises(BadCloud, match="mask"):
        rim_cloud(good, segmenter=lambda f: np.zeros((3, 3), bool))
    with pytest.raises(BadCloud, match="depth_range"):
        rim_cloud(good, depth_range=(2.0, 1.0))
    with pytest.raises(BadCloud, match="depth_range"):
        rim_cloud(good, depth_range=(0.0, float("nan")))
    bad = RgbdFrame(camera=cam.info(), color=np.zeros((10, 10, 3), np.uint8), depth=np.zeros((48, 64), np.uint16))
    with pytest.raises(BadCloud, match="does not match"):
        rim_cloud(bad)
    other = RgbdFrame(camera=CameraInfo(width=640, height=480), color=good.color, depth=good.depth)
    with pytest.raises(BadCloud, match="camera info"):
        rim_cloud(other)
    with pytest.raises(BadCloud, match="hue band"):
        hsv_segmenter([(170, 200)])
