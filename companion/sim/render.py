"""Ray-cast renderer of the textured world (open3d RaycastingScene, headless, CPU).

One ray per pixel, cast once per frame. Ray directions are precomputed from the camera model
(OpenCV pinhole; with distortion the ray of each *distorted* pixel comes from
cv2.undistortPoints, so the image is rendered directly through the lens model). Texture lookup
is a vectorised gather with nearest-mipmap level chosen from the pixel footprint (no aliasing
shimmer when the texture is minified). Flat Lambert shading with a sun and sky ambient.
Sensor model: exposure gain + gamma (lighting variants), shot/read noise, optional motion blur
(a line kernel along the image motion of the scene during the exposure).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d

from companion.sim.textures import TILE_PX, Textures
from companion.sim.world import Mesh
from slam.types import CameraModel

_N_MIP = 6
_LOG2_TILE = int(np.log2(TILE_PX))


@dataclass(frozen=True)
class Lighting:
    """Exposure gain (1 normal, > 1 over-exposed, < 1 under-exposed), display gamma, noise σ in DN."""

    name: str = "normal"
    gain: float = 1.0
    gamma: float = 1.0
    read_noise_dn: float = 2.0
    shot_noise: float = 0.35   # σ = shot_noise · sqrt(signal DN)
    sun_elevation_deg: float = 50.0
    sun_azimuth_deg: float = 135.0

    @staticmethod
    def named(name: str) -> "Lighting":
        presets = {
            "normal": Lighting(),
            "bright": Lighting("bright", gain=2.3, gamma=0.8, read_noise_dn=2.0, sun_elevation_deg=65.0),
            "dark": Lighting("dark", gain=0.3, gamma=0.8, read_noise_dn=3.0, shot_noise=0.5, sun_elevation_deg=15.0),
        }
        if name not in presets:
            raise ValueError(f"unknown lighting {name!r}; choose one of {sorted(presets)}")
        return presets[name]


@dataclass(frozen=True)
class RenderOutput:
    image_bgr: np.ndarray        # (H, W, 3) uint8
    depth_m: np.ndarray          # (H, W) float32 ray length to the hit (inf: sky)
    points_enu: np.ndarray       # (H, W, 3) float32 hit points (nan: sky)
    labels: np.ndarray           # (H, W) uint8 ASPRS label (0: sky)
    element: np.ndarray          # (H, W) int32 building id (-1: none)


def pixel_rays_cam(camera: CameraModel) -> np.ndarray:
    """Unit ray direction in the camera frame for every pixel centre, (H*W, 3) float32, row-major."""
    u, v = np.meshgrid(np.arange(camera.width_px, dtype=np.float64), np.arange(camera.height_px, dtype=np.float64))
    px = np.stack([u.ravel(), v.ravel()], 1)
    if camera.is_distorted:
        xy = cv2.undistortPoints(px.reshape(-1, 1, 2), camera.K, camera.dist).reshape(-1, 2)
    else:
        xy = (px - [camera.cx, camera.cy]) / [camera.fx, camera.fy]
    d = np.c_[xy, np.ones(len(xy))]
    return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def _mip_pyramid(atlas: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flattened mip levels of all textures: (data, level offsets, level sizes)."""
    levels, offs, sizes, off = [], [], [], 0
    cur = atlas
    for _ in range(_N_MIP):
        levels.append(cur.reshape(-1))
        offs.append(off)
        sizes.append(cur.shape[1])
        off += cur.size
        cur = np.stack([cv2.resize(t, (t.shape[1] // 2, t.shape[0] // 2), interpolation=cv2.INTER_AREA) for t in cur])
    return np.concatenate(levels), np.array(offs, np.int64), np.array(sizes, np.int64)


class Renderer:
    """Renders one mesh through one camera. ``render(T_enu_cam)`` → RenderOutput."""

    def __init__(self, mesh: Mesh, textures: Textures, camera: CameraModel, lighting: Lighting = Lighting(),
                 seed: int = 0):
        self.camera = camera
        self.lighting = lighting
        self._mesh = mesh
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                                  o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
        self._rays_cam = pixel_rays_cam(camera)
        self._mip, self._mip_off, _ = _mip_pyramid(textures.atlas)
        self._macro = textures.macro
        # per-triangle colour = tint · Lambert(sun) + sky ambient (flat shading)
        el, az = np.radians(lighting.sun_elevation_deg), np.radians(lighting.sun_azimuth_deg)
        sun = np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])
        n = mesh.triangle_normals()
        lam = np.clip(n @ sun, 0, None)
        self._shade_bgr = (mesh.tint_bgr * (0.35 + 0.75 * lam)[:, None]).astype(np.float32)
        # per-triangle tables with a sentinel row (index n_tri) for rays that hit nothing
        n = self._n_tri = len(mesh.triangles)
        A = np.concatenate([mesh.uv_affine.reshape(n, 8), np.zeros((1, 8))]).astype(np.float32)
        self._A = [np.ascontiguousarray(A[:, k]) for k in range(8)]
        texel_per_m = np.linalg.norm(mesh.uv_affine[:, 0, :3], axis=1)
        self._texel_per_m_over_f = np.append(texel_per_m / camera.fx, 1.0).astype(np.float32)
        tex = np.append(mesh.tex.astype(np.int64), 0)
        sizes = TILE_PX >> np.arange(_N_MIP)
        self._base = self._mip_off[None, :] + tex[:, None] * (sizes * sizes)[None, :]
        self._macro_tri = np.append(mesh.macro, False)
        self._inv_macro = 1.0 / textures.macro_m_per_px
        self._shade_bgr = np.concatenate([self._shade_bgr, np.zeros((1, 3), np.float32)])
        self._labels = np.append(mesh.labels, 0).astype(np.uint8)
        self._element = np.append(mesh.element, -1).astype(np.int32)
        self._rng = np.random.default_rng(seed)
        self._sky = np.array([235, 215, 200], np.float32)  # BGR, pale sky

    def cast(self, T_enu_cam: np.ndarray):
        """Raw ray cast: (t_hit (N,), prim ids (N,), ray dirs ENU (N, 3)), N = H*W."""
        R, c = T_enu_cam[:3, :3].astype(np.float32), T_enu_cam[:3, 3]
        d = self._rays_cam @ R.T
        rays = np.empty((len(d), 6), np.float32)
        rays[:, :3] = c
        rays[:, 3:] = d
        ans = self._scene.cast_rays(o3d.core.Tensor(rays))
        return ans["t_hit"].numpy(), ans["primitive_ids"].numpy(), d, ans["primitive_normals"].numpy()

    def cast_one(self, T_enu_cam: np.ndarray, ray_cam: np.ndarray):
        """One ray (camera-frame direction): (t_hit, prim id, unit direction ENU, normal)."""
        d = T_enu_cam[:3, :3] @ (ray_cam / np.linalg.norm(ray_cam))
        ans = self._scene.cast_rays(o3d.core.Tensor(np.r_[T_enu_cam[:3, 3], d][None].astype(np.float32)))
        return float(ans["t_hit"].numpy()[0]), int(ans["primitive_ids"].numpy()[0]), d, ans["primitive_normals"].numpy()[0]

    def render(self, T_enu_cam: np.ndarray, motion_px: tuple[float, float] | None = None) -> RenderOutput:
        cam = self.camera
        H, W = cam.height_px, cam.width_px
        t, prim, d, nrm = self.cast(T_enu_cam)
        hit = np.isfinite(t)
        all_hit = bool(hit.all())
        # misses index the sentinel row (last) of every per-triangle table; no boolean copies
        pi = prim.astype(np.int64) if all_hit else np.where(hit, prim, self._n_tri).astype(np.int64)
        th = t if all_hit else np.where(hit, t, 0.0).astype(np.float32)
        p = T_enu_cam[:3, 3].astype(np.float32) + d * th[:, None]
        u = self._A[0][pi] * p[:, 0] + self._A[1][pi] * p[:, 1] + self._A[2][pi] * p[:, 2] + self._A[3][pi]
        v = self._A[4][pi] * p[:, 0] + self._A[5][pi] * p[:, 1] + self._A[6][pi] * p[:, 2] + self._A[7][pi]
        # nearest mip level: texels per pixel = range/f / cos(incidence) · texels per metre
        cos_inc = np.abs(nrm[:, 0] * d[:, 0] + nrm[:, 1] * d[:, 1] + nrm[:, 2] * d[:, 2])
        foot = th * self._texel_per_m_over_f[pi] / np.maximum(cos_inc, 0.2)
        lvl = np.clip(np.log2(np.maximum(foot, 1e-6)) + 0.5, 0, _N_MIP - 1).astype(np.int64)
        shift = lvl  # level l has TILE_PX >> l texels per side
        size = TILE_PX >> lvl
        ui = (u.astype(np.int64) >> shift) & (size - 1)
        vi = (v.astype(np.int64) >> shift) & (size - 1)
        gray = self._mip[self._base[pi, lvl] + ((vi << (_LOG2_TILE - lvl)) | ui)].astype(np.float32)
        M = self._macro.shape[0]
        mx = (p[:, 0] * self._inv_macro).astype(np.int64) % M
        my = (p[:, 1] * self._inv_macro).astype(np.int64) % M
        gray *= np.where(self._macro_tri[pi], self._macro[my, mx], 1.0)
        img = gray[:, None] * self._shade_bgr[pi]
        if not all_hit:
            img[~hit] = self._sky
        img = img.reshape(H, W, 3)
        if motion_px is not None and np.hypot(*motion_px) >= 1.0:
            img = _motion_blur(img, motion_px)
        image = self._expose(img)
        pts = p.reshape(H, W, 3)
        if not all_hit:
            pts = pts.copy()
            pts[~hit.reshape(H, W)] = np.nan
        return RenderOutput(image, t.reshape(H, W), pts, self._labels[pi].reshape(H, W), self._element[pi].reshape(H, W))

    def _expose(self, radiance: np.ndarray) -> np.ndarray:
        L = self.lighting
        x = radiance * L.gain
        if L.gamma != 1.0:
            x = 255.0 * np.power(np.clip(x / 255.0, 0, None), L.gamma)
        sigma = np.sqrt(L.read_noise_dn ** 2 + L.shot_noise ** 2 * np.clip(x[..., :1], 0, None))
        x = x + sigma * self._rng.standard_normal(x.shape[:2], dtype=np.float32)[..., None]
        return np.clip(x, 0, 255).astype(np.uint8)


def _motion_blur(img: np.ndarray, motion_px: tuple[float, float]) -> np.ndarray:
    """Average along the image motion during the exposure (a line kernel, cv2.filter2D)."""
    dx, dy = motion_px
    n = int(np.ceil(np.hypot(dx, dy))) | 1
    k = np.zeros((n, n), np.float32)
    c = n // 2
    for s in np.linspace(-0.5, 0.5, 2 * n):
        k[int(round(c + s * dy)) % n, int(round(c + s * dx)) % n] += 1
    return cv2.filter2D(img, -1, k / k.sum(), borderType=cv2.BORDER_REFLECT)
