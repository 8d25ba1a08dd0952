"""The simulated D455: depth that matches the geometry exactly (checked against MuJoCo's own ray
casting through each pixel), the rig's intrinsics honoured, the red rim where the true rim is, real
occlusion, and a noise model that behaves like a stereo camera's."""

import mujoco
import numpy as np
import pytest

from bagit.common.geometry import points_to_polyline_distance, transform_points
from bagit.common.rig import CameraConfig, RigConfig
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.sim.camera import DepthNoise, _PixelRays, add_depth_noise
from bagit.services.sim.objects import object_parts
from bagit.services.sim.world import SimWorld


@pytest.fixture(scope="module")
def coffee():
    return Scenario.from_file(find_scenario("exp01-coffee-box"))


def back_project(depth_m: np.ndarray, info) -> np.ndarray:
    """(n, 3) camera-frame points of the valid pixels of `depth_m (H, W)`."""
    v, u = np.nonzero(depth_m > 0)
    z = depth_m[v, u]
    return np.stack([(u - info.cx) / info.fx * z, (v - info.cy) / info.fy * z, z], axis=1)


def ray_cast_depth(w: SimWorld, info, us: np.ndarray, vs: np.ndarray) -> np.ndarray:
    """z-depth of pixel centres (us, vs) by MuJoCo's ray casting (geoms only: it ignores flexes)."""
    T = info.extrinsics()
    a = np.stack([(us - info.cx) / info.fx, (vs - info.cy) / info.fy, np.ones(len(us))], axis=1)
    vec = (a @ T[:3, :3].T) / np.linalg.norm(a, axis=1, keepdims=True)
    dist = np.zeros(len(us))
    geom = np.zeros(len(us), dtype=np.int32)
    mujoco.mj_multiRay(w.model, w.data, T[:3, 3].copy(), vec.ravel().copy(), None, 1, -1, geom, dist, None, len(us), 10.0)
    return np.where(dist > 0, dist / np.linalg.norm(a, axis=1), 0.0)


def check_depth_against_rays(w: SimWorld) -> tuple[float, float, int]:
    """Noise-free frame vs ray casting on a pixel grid: (share agreeing within 1 mm, share rendered
    farther than the rays by > 2 mm, pixels seeing the object)."""
    w.noise = DepthNoise(enabled=False)
    f = w.render_rgbd(0)
    info = f.camera
    vs, us = np.mgrid[0 : info.height : 4, 0 : info.width : 4]
    us, vs = us.ravel().astype(float), vs.ravel().astype(float)
    rendered = f.depth[vs.astype(int), us.astype(int)] * info.depth_scale
    cast = ray_cast_depth(w, info, us, vs)
    both = (rendered > 0) & (cast > 0)
    diff = rendered[both] - cast[both]
    agree = np.mean(np.abs(diff) < 0.001 + 1e-9)  # depth is stored in whole mm
    too_far = np.mean(diff > 0.002)  # nearer is fine: the bag (a flex) occludes, and rays ignore flexes
    pts = transform_points(info.extrinsics(), back_project(f.depth * info.depth_scale, info))
    on_object = sum(int((p.depth(pts) > -0.003).sum()) for p in object_parts(w.scenario.object))
    return agree, too_far, on_object


def test_depth_is_the_ray_cast_geometry(coffee):
    w = SimWorld(coffee, seed=0)
    w.step(0.3)
    agree, too_far, on_object = check_depth_against_rays(w)
    assert agree > 0.9 and too_far < 0.002
    assert on_object > 1000  # the box is in view, where its geometry is
    w.close()


def test_the_rig_intrinsics_are_honoured_exactly_at_another_resolution(coffee):
    """fx != fy, an off-centre principal point, 320 x 240: lower resolution is a setting."""
    cam = CameraConfig(width=320, height=240, fx=200.0, fy=210.0, cx=170.0, cy=112.0, position=(0.5, 0.1, 1.2))
    rig = RigConfig(camera=cam)
    w = SimWorld(coffee, rig, seed=0)
    f = w.render_rgbd(0)
    assert f.color.shape == (240, 320, 3) and f.depth.shape == (240, 320)
    assert f.camera == cam.info()
    agree, too_far, _ = check_depth_against_rays(w)
    assert agree > 0.9 and too_far < 0.002
    w.close()


def test_red_rim_pixels_fall_on_the_true_rim(coffee):
    w = SimWorld(coffee, seed=1)
    w.step(0.5)
    f = w.render_rgbd(0)
    assert f.color.shape == (480, 640, 3) and f.color.dtype == np.uint8 and f.depth.dtype == np.uint16
    c = f.color.astype(int)
    red = (c[..., 0] > 120) & (c[..., 1] < 70) & (c[..., 2] < 70) & (f.depth > 0)
    assert red.sum() > 300
    depth = np.where(red, f.depth * f.camera.depth_scale, 0.0)
    pts = transform_points(f.camera.extrinsics(), back_project(depth, f.camera))
    d = points_to_polyline_distance(pts, w.true_rim())
    # the rim's 6 mm binding is seen from above, plus depth noise of ~2 mm at 1.2 m
    assert np.median(d) < 0.009 and np.percentile(d, 90) < 0.015
    w.close()


def test_the_gripper_occludes_what_is_behind_it(coffee):
    w = SimWorld(coffee, seed=0)
    w.noise = DepthNoise(enabled=False)
    f = w.render_rgbd(0)
    info = f.camera
    T_cw = np.linalg.inv(info.extrinsics())
    for name in ("left", "right"):
        flange = (w.mount_poses()[name] @ np.linalg.inv(w.rig.arms[name].T_flange_mount()))[:3, 3]
        p = T_cw[:3, :3] @ flange + T_cw[:3, 3]
        u, v = int(round(info.fx * p[0] / p[2] + info.cx)), int(round(info.fy * p[1] / p[2] + info.cy))
        seen = f.depth[v, u] * info.depth_scale
        assert abs(seen - p[2]) < 0.05  # the flange's disc, not the table a metre behind it
        rgb = f.color[v, u].astype(int)
        assert rgb.min() > 60 and rgb.max() - rgb.min() < 20  # and it is the grey flange that shows
    w.close()


def test_a_solid_bag_has_no_red_edge():
    s = Scenario.from_file(find_scenario("exp09-tea-bucket-solid-bag"))
    w = SimWorld(s, seed=0)
    f = w.render_rgbd(0)
    c = f.color.astype(int)
    assert ((c[..., 0] > 120) & (c[..., 1] < 70) & (c[..., 2] < 70)).sum() < 20
    w.close()


def test_frames_are_seeded_by_world_seed_and_sequence(coffee):
    w = SimWorld(coffee, seed=4)
    w.step(0.1)
    a, b, c = w.render_rgbd(7), w.render_rgbd(7), w.render_rgbd(8)
    assert np.array_equal(a.depth, b.depth) and np.array_equal(a.color, b.color)
    assert not np.array_equal(a.depth, c.depth) and np.array_equal(a.color, c.color)
    assert a.seq == 7 and a.stamp == pytest.approx(w.time)
    w.close()


# -- the noise model on synthetic depth images ---------------------------------------------------

CAM = CameraConfig()
RAYS = _PixelRays(CAM)


def test_noise_grows_with_distance_like_stereo():
    noise = DepthNoise()
    rng = np.random.default_rng(0)
    for z in (1.0, 2.0):
        out = add_depth_noise(np.full((480, 640), z), noise, rng, RAYS)
        ok = out > 0
        assert 0.99 < ok.mean() < 1.0  # a few speckle holes
        assert np.std(out[ok] - z) == pytest.approx(noise.sigma_at_1m * z**2, rel=0.05)


def test_depth_edges_lose_pixels_and_fly_some():
    z = np.full((480, 640), 1.5)
    z[:, :320] = 1.0  # a step: foreground on the left
    out = add_depth_noise(z, DepthNoise(sigma_at_1m=0.0, speckle_dropout=0.0), np.random.default_rng(1), RAYS)
    edge = out[:, 318:322]
    assert (edge == 0).mean() > 0.2  # holes along the edge
    flying = (edge > 1.01) & (edge < 1.49)
    assert flying.sum() > 20  # points between the two surfaces
    away = np.concatenate([out[:, :317].ravel(), out[:, 323:].ravel()])
    assert np.all((away == 1.0) | (away == 1.5))  # nothing happens away from the edge


def test_grazing_surfaces_lose_their_returns():
    info = CAM.info()
    rows = np.arange(480, dtype=float)
    rng = np.random.default_rng(2)
    for angle_deg, kept in ((88.0, (0.0, 0.02)), (45.0, (0.99, 1.0))):
        # a plane tilted about the camera's x axis, through (0, 0, 1.5): z(v) from its slope
        t = np.tan(np.radians(angle_deg))
        y = (rows - info.cy) / info.fy
        z = 1.5 / (1 - t * y)
        z = np.where((z > 0.5) & (z < 5.0), z, 0.0)
        img = np.repeat(z[:, None], 640, axis=1)
        out = add_depth_noise(img, DepthNoise(sigma_at_1m=0.0, speckle_dropout=0.0), rng, RAYS)
        band = (img > 1.4) & (img < 1.6)  # rows seen near the middle, away from the range cuts
        assert kept[0] <= (out[band] > 0).mean() <= kept[1], angle_deg


def test_out_of_range_is_no_return():
    z = np.full((480, 640), 0.3)
    z[:, 320:] = 7.0
    out = add_depth_noise(z, DepthNoise(), np.random.default_rng(3), RAYS)
    assert np.all(out == 0)


def _reference_noise(depth: np.ndarray, noise: DepthNoise, rng: np.random.Generator, rays: _PixelRays) -> np.ndarray:
    """The noise model as plain formulas (the code before it was computed in place)."""

    def slope(z, axis, rel):
        d = np.diff(z, axis=axis)
        pad = [(0, 0), (0, 0)]
        pad[axis] = (1, 0)
        before = np.pad(d, pad, mode="edge")
        pad[axis] = (0, 1)
        after = np.pad(d, pad, mode="edge")
        ab, aa = np.abs(before), np.abs(after)
        own = np.where(ab < aa, before, after)
        big, small = np.maximum(ab, aa), np.minimum(ab, aa)
        return own, (big > rel * z) & (big > 3.0 * small)

    z = np.asarray(depth, dtype=np.float32)
    valid = (z >= noise.min_range_m) & (z <= noise.max_range_m)
    z = np.where(valid, z, np.float32(0.0))
    zu, edge_u = slope(z, 1, noise.edge_jump)
    zv, edge_v = slope(z, 0, noise.edge_jump)
    edge = valid & (edge_u | edge_v)
    a, b = rays.fx * zu, rays.fy * zv
    nz = a * rays.x + b * rays.y + z
    cos_inc = z / (np.sqrt(a * a + b * b + nz * nz) * rays.norm + np.float32(1e-12))
    cos_start, cos_full = np.cos(np.radians(noise.grazing_start_deg)), np.cos(np.radians(noise.grazing_full_deg))
    p_graze = np.clip((cos_start - cos_inc) / (cos_start - cos_full), 0.0, 1.0)
    u = rng.random(z.shape, dtype=np.float32)
    out = z + rng.standard_normal(z.shape, dtype=np.float32) * np.float32(noise.sigma_at_1m) * z * z
    drop = (edge & (u < noise.edge_dropout)) | (u < p_graze) | (u > 1.0 - noise.speckle_dropout)
    fly = edge & (u >= noise.edge_dropout) & (u < noise.edge_dropout + noise.flying_fraction * (1.0 - noise.edge_dropout))
    r, c = np.nonzero(fly)
    if len(r):
        h, wd = z.shape
        nb = np.stack([z[r, c], z[np.maximum(r - 1, 0), c], z[np.minimum(r + 1, h - 1), c], z[r, np.maximum(c - 1, 0)], z[r, np.minimum(c + 1, wd - 1)]])
        nb = np.where(nb > 0, nb, z[r, c])
        w = (u[r, c] - noise.edge_dropout) / (noise.flying_fraction * (1.0 - noise.edge_dropout))
        lo, hi = nb.min(axis=0), nb.max(axis=0)
        out[r, c] = lo + w * (hi - lo)
    out[drop | ~valid] = 0.0
    return out


def test_the_noise_computed_in_place_is_the_plain_formulas_bit_for_bit(coffee):
    """`add_depth_noise` works in place for speed; a rendered scene's noisy depth is the same bits as the formulas'."""
    with SimWorld(coffee, seed=0) as w:
        w.step(0.2)
        w.render_rgbd(0)
        _, z = w._renderer.render(w.data)
        rays = w._renderer.rays
    assert (z > 0).mean() > 0.5
    for seq in range(3):
        got = add_depth_noise(z, DepthNoise(), np.random.default_rng([0, seq]), rays)
        want = _reference_noise(z, DepthNoise(), np.random.default_rng([0, seq]), rays)
        assert got.dtype == want.dtype and np.array_equal(got, want)
    assert np.count_nonzero(got != z) > 0.5 * z.size  # the noise did something


def _reference_units(z: np.ndarray, depth_scale: float) -> np.ndarray:
    """Metric depth to uint16 units as plain formulas (the code before it was computed in place)."""
    units = np.round(z / np.float32(depth_scale))
    return np.where(units <= 65535, units, 0).astype(np.uint16)


@pytest.mark.parametrize("bands", [1, 2, 3, 7])
def test_the_noise_in_row_bands_is_the_plain_formulas_bit_for_bit(coffee, monkeypatch, bands):
    """However many bands the rows are cut into (odd splits included), every pixel gets the formulas' bits."""
    from bagit.services.sim import camera

    monkeypatch.setattr(camera, "NOISE_BANDS", bands)
    monkeypatch.setattr(camera, "_workers", None)  # a pool with bands - 1 workers
    with SimWorld(coffee, seed=0) as w:
        w.step(0.2)
        color, z = w.render_true()
        rays = w._renderer.rays
    z = z.copy()
    z[100:140, 300:340] = 7.0  # out of range: a hole with edges around it ...
    z[240:260, :320] *= 1.2  # ... steps on the band boundaries (2 bands: rows 239 | 240; 3: 159 | 160) ...
    z[160:200, 320:] *= 0.8
    z[300:310, :] = 0.2  # ... and rows too near
    got = add_depth_noise(z, DepthNoise(), np.random.default_rng([3, 9]), rays)
    want = _reference_noise(z, DepthNoise(), np.random.default_rng([3, 9]), rays)
    assert np.array_equal(got, want)


def test_a_frame_is_the_plain_formulas_bit_for_bit_whatever_order_the_frames_come_in(coffee):
    """The draws made ahead for seq + 1 are frame seq + 1's; any other seq gets its own: the frame never
    depends on which frames came before. Depth linearisation and units are the plain formulas too."""
    from bagit.services.sim.camera import RgbdRenderer

    with SimWorld(coffee, seed=5) as w:
        w.step(0.2)
        _, z = w.render_true()
        r: RgbdRenderer = w._renderer
        n, f = r._near, r._far
        buf = np.flipud(r._depth).astype(np.float64)
        ref = (f * n) / (buf * (f - n) + n)
        ref[buf <= 0.0] = 0.0
        assert np.array_equal(z, ref.astype(np.float32))
        scale = w.rig.camera.info().depth_scale
        for seq in (0, 1, 2, 7, 3, 4, 4, 0):
            got = w.render_rgbd(seq)
            want = _reference_units(_reference_noise(z, DepthNoise(), np.random.default_rng([5, seq]), r.rays), scale)
            assert got.seq == seq and np.array_equal(got.depth, want), seq
        w.noise = off = DepthNoise(enabled=False)
        in_range = np.where((z >= off.min_range_m) & (z <= off.max_range_m), z, np.float32(0.0))
        assert np.array_equal(w.render_rgbd(5).depth, _reference_units(in_range, scale))
