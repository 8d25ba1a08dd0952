"""The simulated eye-to-hand RGB-D camera: colour and depth from one offscreen OpenGL render of the
MuJoCo scene (flexes included, which MuJoCo's ray casting ignores), and a D455-like depth noise model.

The MJCF camera carries the rig's pinhole intrinsics exactly (focal lengths and principal point in
pixels, OpenCV convention: pixel centres at integer coordinates), so a depth pixel (u, v, z)
back-projects with `CameraInfo.K()` onto the rendered geometry. Depth is z along the optical axis,
metric, 0 where there is no return.
"""

from __future__ import annotations

import os
import sys
import weakref
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace

import mujoco
import numpy as np

from bagit.common.rig import CameraConfig
from bagit.services.sim.scene import CAMERA_NAME


@dataclass
class DepthNoise:
    """How a D455-like stereo depth camera degrades the true depth."""

    sigma_at_1m: float = 0.0015  # depth noise std at 1 m (m); grows with z^2, as stereo error does
    min_range_m: float = 0.4  # nearer than this: no return (the D455's minimum depth)
    max_range_m: float = 6.0
    edge_jump: float = 0.04  # a neighbour this much nearer or farther (relative to z) marks a depth edge
    edge_dropout: float = 0.5  # share of depth-edge pixels that come back empty
    flying_fraction: float = 0.25  # share of the other edge pixels that float between the two surfaces
    grazing_start_deg: float = 72.0  # incidence angles beyond this start to lose their returns ...
    grazing_full_deg: float = 84.0  # ... and beyond this all of them
    speckle_dropout: float = 0.002  # isolated holes anywhere (matching failures)
    enabled: bool = True  # False: the true depth, only cut to the sensor's range (for tests and ground truth)

    def scaled(self, k: float) -> DepthNoise:
        """This noise with its standard deviation times `k` (a scenario's sim.camera.depth_noise); the
        dropouts and flying pixels, which come from the scene's edges and angles, stay as they are."""
        return replace(self, sigma_at_1m=self.sigma_at_1m * k)


class _PixelRays:
    """Per-pixel normalised image coordinates for a camera (cached: they never change)."""

    def __init__(self, cam: CameraConfig):
        info = cam.info()
        u = (np.arange(info.width, dtype=np.float32) - info.cx) / info.fx
        v = (np.arange(info.height, dtype=np.float32) - info.cy) / info.fy
        self.x, self.y = np.meshgrid(u, v)  # (H, W) each
        self.norm = np.sqrt(self.x**2 + self.y**2 + 1.0)
        self.fx, self.fy = np.float32(info.fx), np.float32(info.fy)


def _slope(z: np.ndarray, axis: int, rel: float) -> tuple[np.ndarray, np.ndarray]:
    """Along `axis` of `z (H, W)`: the pixel's own slope (smaller one-sided difference, per pixel),
    and whether a step (a difference over `rel` * z on one side, over three times the other) is next to it.

    The differences go once into `d`, padded by one at each end (the first pixel taking its
    neighbour's, the last likewise): `before` = z[i] - z[i-1] and `after` = z[i+1] - z[i] are views of it.
    """
    n = z.shape[axis]
    sl = lambda a, b: (slice(a, b), slice(None)) if axis == 0 else (slice(None), slice(a, b))  # noqa: E731
    shape = list(z.shape)
    shape[axis] = n + 1
    d = np.empty(shape, dtype=z.dtype)  # (H+1, W) or (H, W+1)
    np.subtract(z[sl(1, n)], z[sl(0, n - 1)], out=d[sl(1, n)])
    d[sl(0, 1)] = d[sl(1, 2)]
    d[sl(n, n + 1)] = d[sl(n - 1, n)]
    ad = np.abs(d)
    before, after = d[sl(0, n)], d[sl(1, n + 1)]
    ab, aa = ad[sl(0, n)], ad[sl(1, n + 1)]
    own = np.where(ab < aa, before, after)
    big = np.maximum(ab, aa)
    small = np.minimum(ab, aa)
    small *= 3.0
    step = big > small
    big_rel = big > rel * z
    step &= big_rel
    return own, step


NOISE_BANDS = 2  # row bands of a frame's noise computed at once (numpy releases the GIL in its loops)


def noise_draws(rng: np.random.Generator, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The noise model's random draws for a depth image of `shape (H, W)`, in the order it makes them:
    uniform `u (H, W)` float32, then standard normal `(H, W)` float32."""
    u = rng.random(shape, dtype=np.float32)
    return u, rng.standard_normal(shape, dtype=np.float32)


_workers: tuple[int, ThreadPoolExecutor] | None = None


def _worker_pool() -> ThreadPoolExecutor:
    """The noise's worker threads (one process-wide pool, made anew in a forked child, whose threads did not survive)."""
    global _workers
    if _workers is None or _workers[0] != os.getpid():
        _workers = (os.getpid(), ThreadPoolExecutor(max_workers=NOISE_BANDS - 1, thread_name_prefix="depth-noise"))
    return _workers[1]


class DrawsAhead:
    """The random draws of the next frame, made on a worker thread while the caller does other work.

    `take(seed, seq, shape)` returns frame `seq`'s draws, those made ahead when they are for the same
    (seed, seq, shape), else made now: the same generator, the same calls, so the same bits either way.
    """

    def __init__(self) -> None:
        self._key: tuple[int, int, tuple[int, int]] | None = None
        self._future: Future[tuple[np.ndarray, np.ndarray]] | None = None

    @staticmethod
    def _make(seed: int, seq: int, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        return noise_draws(np.random.default_rng([seed, seq]), shape)

    def take(self, seed: int, seq: int, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        future, key = self._future, self._key
        self._future = self._key = None
        if future is not None and key == (seed, seq, shape):
            return future.result()
        return self._make(seed, seq, shape)

    def ahead(self, seed: int, seq: int, shape: tuple[int, int]) -> None:
        """Start making frame `seq`'s draws (a frame taken for another seq discards them)."""
        self._key = (seed, seq, shape)
        self._future = _worker_pool().submit(self._make, seed, seq, shape)


def add_depth_noise(
    depth: np.ndarray,
    noise: DepthNoise,
    rng: np.random.Generator | None,
    rays: _PixelRays,
    draws: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Noisy metric depth `(H, W)` float32 from true metric depth `(H, W)` (0 = no return).

    Noise std sigma_at_1m * z^2; holes at depth edges, at grazing incidence (from the true surface's
    normal, estimated from the depth slope) and a few anywhere; flying pixels at edges. The random
    numbers are `noise_draws(rng, shape)`, or `draws` when given (made ahead: `DrawsAhead`).

    Every pixel's value depends only on its own and its 4 neighbours' depth and its own draws, so
    the image is computed in NOISE_BANDS row bands at once (each band with its neighbour rows), the
    draws made whole beforehand: the same float32 operations on each pixel, so the same bits
    (`tests/sim/test_sim_camera.py` checks it against the plain formulas).
    """
    z_in = np.asarray(depth, dtype=np.float32)
    if not noise.enabled:
        valid = (z_in >= noise.min_range_m) & (z_in <= noise.max_range_m)
        return np.where(valid, z_in, np.float32(0.0))
    if draws is None:
        if rng is None:
            raise ValueError("add_depth_noise needs a generator or its draws")
        draws = noise_draws(rng, z_in.shape)
    u, out = draws  # `out` is computed in place over the normal draws
    h = z_in.shape[0]
    edges = [h * k // NOISE_BANDS for k in range(NOISE_BANDS + 1)]
    bands = [(edges[k], edges[k + 1]) for k in range(NOISE_BANDS) if edges[k + 1] > edges[k]]
    pool = _worker_pool() if len(bands) > 1 else None
    futures = [pool.submit(_noise_band, z_in, noise, rays, u, out, r0, r1) for r0, r1 in bands[1:]] if pool else []
    _noise_band(z_in, noise, rays, u, out, *bands[0])
    for f in futures:
        f.result()
    return out


def _noise_band(z_in: np.ndarray, noise: DepthNoise, rays: _PixelRays, u_all: np.ndarray, out_all: np.ndarray, r0: int, r1: int) -> None:
    """Rows [r0, r1) of the noisy depth into `out_all (H, W)` (which holds the normal draws), from the
    true depth `z_in (H, W)` and the uniform draws `u_all (H, W)`. Plain formulas in the comments: the
    same float32 operations in the same order, computed in place where it can be."""
    h = z_in.shape[0]
    h0, h1 = max(r0 - 1, 0), min(r1 + 1, h)  # the band and its neighbour rows (for the vertical slope)
    i0, i1 = r0 - h0, r1 - h0  # the band's own rows within them
    zh = z_in[h0:h1]
    valid_h = (zh >= noise.min_range_m) & (zh <= noise.max_range_m)
    zh = np.where(valid_h, zh, np.float32(0.0))  # (h1 - h0, W)
    z, valid = zh[i0:i1], valid_h[i0:i1]
    u, out = u_all[r0:r1], out_all[r0:r1]
    # One-sided differences to each neighbour: a surface's slope is the smaller of the two (a pixel
    # belongs to one side of a step); a step is a big difference on one side only.
    zu, edge_u = _slope(z, axis=1, rel=noise.edge_jump)
    zv, edge_v = _slope(zh, axis=0, rel=noise.edge_jump)
    zv, edge_v = zv[i0:i1], edge_v[i0:i1]
    edge = edge_u
    edge |= edge_v
    edge &= valid
    # Surface normal from the slope (n ~ (-fx z_u, -fy z_v, fx z_u x + fy z_v y + z)): cos of incidence.
    a = np.multiply(rays.fx, zu, out=zu)  # a = fx * zu
    b = np.multiply(rays.fy, zv, out=zv)  # b = fy * zv
    nz = a * rays.x[r0:r1]  # nz = a * x + b * y + z
    nz += b * rays.y[r0:r1]
    nz += z
    den = a * a  # den = sqrt(a * a + b * b + nz * nz) * norm + 1e-12
    den += b * b
    nz *= nz
    den += nz
    np.sqrt(den, out=den)
    den *= rays.norm[r0:r1]
    den += np.float32(1e-12)
    cos_inc = np.divide(z, den, out=den)
    cos_start = np.cos(np.radians(noise.grazing_start_deg))
    cos_full = np.cos(np.radians(noise.grazing_full_deg))
    # p_graze = clip((cos_start - cos_inc) / (cos_start - cos_full), 0, 1), in float64; u in [0, 1)
    # is below it exactly when it is below the unclipped ratio, so the clip is left out.
    p_graze = np.subtract(cos_start, cos_inc, dtype=np.float64)
    p_graze /= cos_start - cos_full
    out *= np.float32(noise.sigma_at_1m)  # out = z + normal * sigma * z * z
    out *= z
    out *= z
    out += z
    drop = u < p_graze  # drop = (edge & (u < edge_dropout)) | (u < p_graze) | (u > 1 - speckle_dropout)
    drop |= u > 1.0 - noise.speckle_dropout
    low = u < noise.edge_dropout
    drop |= edge & low
    # fly = edge & (u >= edge_dropout) & (u < edge_dropout + flying_fraction * (1 - edge_dropout))
    fly = u < noise.edge_dropout + noise.flying_fraction * (1.0 - noise.edge_dropout)
    fly &= ~low
    fly &= edge
    r, c = np.nonzero(fly)
    if len(r):
        # somewhere between the nearest and the farthest surface around the pixel (rows of zh: +i0)
        rh, wd = r + i0, z.shape[1]
        up, down = np.maximum(rh - 1, 0), np.minimum(rh + 1, h1 - h0 - 1)
        nb = np.stack([zh[rh, c], zh[up, c], zh[down, c], zh[rh, np.maximum(c - 1, 0)], zh[rh, np.minimum(c + 1, wd - 1)]])
        nb = np.where(nb > 0, nb, zh[rh, c])
        w = (u[r, c] - noise.edge_dropout) / (noise.flying_fraction * (1.0 - noise.edge_dropout))  # uniform in [0, 1)
        lo, hi = nb.min(axis=0), nb.max(axis=0)
        out[r, c] = lo + w * (hi - lo)
    drop |= ~valid
    out[drop] = 0.0


def depth_units(z: np.ndarray, depth_scale: float) -> np.ndarray:
    """Depth `(H, W)` uint16 in `depth_scale` units (0 = no return, and beyond 65535 units) from metric
    `z (H, W)` float32, which it overwrites: units = round(z / depth_scale), where(units <= 65535, units, 0)."""
    units = np.divide(z, np.float32(depth_scale), out=z)
    np.round(units, out=units)
    units[~(units <= 65535)] = 0
    return units.astype(np.uint16)


def _gl_context(width: int, height: int):
    """An offscreen OpenGL context: MuJoCo's choice (MUJOCO_GL), or OSMesa on a Linux box without a
    display when MuJoCo was imported before MUJOCO_GL could default to it."""
    cls = mujoco.GLContext
    if sys.platform.startswith("linux") and not os.environ.get("DISPLAY") and "glfw" in getattr(cls, "__module__", ""):
        from mujoco.osmesa import GLContext as OsmesaContext

        return OsmesaContext(width, height)
    return cls(width, height)


def _free(gl, ctx) -> None:
    """Release an MjrContext and its GL context (in that order, with the context current)."""
    try:
        gl.make_current()
        ctx.free()
        gl.free()
    except Exception:  # noqa: BLE001 - at interpreter exit the GL bindings may already be gone
        pass


class RgbdRenderer:
    """Offscreen colour + depth of one MJCF camera; both read back from a single render pass."""

    def __init__(self, model: mujoco.MjModel, cam: CameraConfig, camera_name: str = CAMERA_NAME, max_geom: int = 2000):
        self.width, self.height = cam.width, cam.height
        self._model = model
        self._cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera_name)
        if self._cam_id < 0:
            raise ValueError(f"the model has no camera named {camera_name!r}")
        self._gl = _gl_context(self.width, self.height)
        self._gl.make_current()
        self._ctx = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
        # freed on close(), on garbage collection, or at exit before the GL bindings unload
        self._finalizer = weakref.finalize(self, _free, self._gl, self._ctx)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._ctx)
        self._ctx.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self._scene = mujoco.MjvScene(model, maxgeom=max_geom)
        self._option = mujoco.MjvOption()
        self._mjcam = mujoco.MjvCamera()
        self._mjcam.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._mjcam.fixedcamid = self._cam_id
        self._rect = mujoco.MjrRect(0, 0, self.width, self.height)
        self._rgb = np.empty((self.height, self.width, 3), dtype=np.uint8)
        self._depth = np.empty((self.height, self.width), dtype=np.float32)
        extent = model.stat.extent
        self._near = float(np.float32(model.vis.map.znear * extent))
        self._far = float(np.float32(model.vis.map.zfar * extent))
        self.rays = _PixelRays(cam)

    def render(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """(colour (H, W, 3) uint8 RGB, metric z-depth (H, W) float32, 0 = nothing within the far plane)."""
        if self._ctx is None:
            raise RuntimeError("the renderer is closed")
        mujoco.mjv_updateScene(self._model, data, self._option, None, self._mjcam, mujoco.mjtCatBit.mjCAT_ALL, self._scene)
        self._gl.make_current()
        mujoco.mjr_render(self._rect, self._scene, self._ctx)
        mujoco.mjr_readPixels(self._rgb, self._depth, self._rect, self._ctx)
        color = np.flipud(self._rgb).copy()
        buf = np.flipud(self._depth).astype(np.float64)
        # reversed-z buffer (1 at the near plane, 0 at the far one) -> metric depth:
        # z = (f * n) / (buf * (f - n) + n), 0 where buf <= 0; in float64, in place
        n, f = self._near, self._far
        none = buf <= 0.0
        z = np.multiply(buf, f - n, out=buf)
        z += n
        np.divide(f * n, z, out=z)
        z[none] = 0.0
        return color, z.astype(np.float32)

    def close(self) -> None:
        self._finalizer()
        self._ctx = None
