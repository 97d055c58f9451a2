"""Procedural, seeded, georeferenced city: terrain, roads, buildings, vegetation and clutter.

The world is a triangle mesh in the local ENU frame of ``origin`` (metres), with per-triangle
ASPRS labels (CONTRIBUTING.md: 2 ground, 5 high vegetation, 6 building, 11 road surface,
1 unclassified clutter), element ids (building id, else -1) and texture mapping. The GIS model of the
same site (``companion.sim.gis_export``) is built from the same description minus what a GIS model
does not contain (vegetation, cars), optionally stale.

Building footprints are stored as an outline (CCW) plus convex parts whose union is the outline,
so roofs triangulate by fans without a polygon library.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace

import numpy as np

from companion.sim.textures import TILE_PX, Tex, Textures, make_textures
from gis.geodesy import LocalFrame

GROUND, VEGETATION, BUILDING, ROAD, CLUTTER = 2, 5, 6, 11, 1

#: texel sizes in metres per texel
_TEXEL_GROUND_M = 0.08
_TEXEL_ROOF_M = 0.05
_TEXEL_FACADE_M = 0.05
_ROAD_WIDTH_M = 10.0


@dataclass(frozen=True)
class WorldSpec:
    """Parameters of a procedural site. Sizes in metres, heights above local ground."""

    lat0_deg: float = 47.3769      # default site: Zurich (the digital-twin paper's simulated city)
    lon0_deg: float = 8.5417
    h0_ellipsoid_m: float = 455.0
    n_buildings: int = 40
    block_m: float = 90.0          # road grid spacing
    min_height_m: float = 10.0
    max_height_m: float = 60.0
    relief_m: float = 4.0          # terrain amplitude
    extent_m: float = 1300.0       # terrain side length (the camera sees far when oblique)
    terrain_step_m: float = 10.0
    trees_per_building: float = 3.0
    cars_per_building: float = 1.5

    def __post_init__(self):
        if not 1 <= self.n_buildings <= 400:
            raise ValueError(f"WorldSpec.n_buildings must be in [1, 400], got {self.n_buildings}")
        if not 0 < self.min_height_m <= self.max_height_m:
            raise ValueError(f"WorldSpec heights: need 0 < min_height_m <= max_height_m, got {self.min_height_m}, {self.max_height_m}")


@dataclass(frozen=True)
class Building:
    id: int
    kind: str                    # rect | L | polygon | quad
    outline_enu: np.ndarray      # (N, 2) CCW footprint, metres ENU
    parts: tuple                 # convex (M, 2) CCW polygons whose union is the outline
    ground_z_m: float            # lowest terrain height under the footprint (ENU up)
    height_m: float              # roof above ground_z_m
    facade_tex: int
    roof_tex: int

    @property
    def roof_z_m(self) -> float:
        return self.ground_z_m + self.height_m


@dataclass(frozen=True)
class Tree:
    xy_enu: np.ndarray
    radius_m: float
    height_m: float


@dataclass(frozen=True)
class Car:
    xy_enu: np.ndarray
    yaw_rad: float


@dataclass(frozen=True)
class Road:
    a_enu: np.ndarray  # (2,) centreline start
    b_enu: np.ndarray  # (2,) centreline end
    width_m: float
    z_offset_m: float


@dataclass(frozen=True)
class Terrain:
    """Smooth relief: sum of sinusoids (closed form, so any consumer gets exact heights)."""

    amp_m: np.ndarray      # (K,)
    k_rad_per_m: np.ndarray  # (K, 2)
    phase_rad: np.ndarray  # (K,)
    extent_m: float
    step_m: float

    def height(self, x, y) -> np.ndarray:
        x, y = np.asarray(x, float), np.asarray(y, float)
        arg = x[..., None] * self.k_rad_per_m[:, 0] + y[..., None] * self.k_rad_per_m[:, 1] + self.phase_rad
        return np.sum(self.amp_m * np.sin(arg), axis=-1)


@dataclass
class Mesh:
    """Triangle soup with per-triangle attributes, ENU metres."""

    vertices: np.ndarray   # (V, 3) float64
    triangles: np.ndarray  # (T, 3) int32
    labels: np.ndarray     # (T,) uint8 ASPRS
    element: np.ndarray    # (T,) int32 building id or -1
    tex: np.ndarray        # (T,) int16 texture slot
    uv_affine: np.ndarray  # (T, 2, 4) float32: [u, v] texels = A @ [x, y, z, 1]
    tint_bgr: np.ndarray   # (T, 3) float32
    macro: np.ndarray      # (T,) bool: modulate with the site-wide albedo map

    @staticmethod
    def concat(parts: list["Mesh"]) -> "Mesh":
        offs = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
        return Mesh(
            vertices=np.concatenate([p.vertices for p in parts]),
            triangles=np.concatenate([p.triangles + o for p, o in zip(parts, offs)]).astype(np.int32),
            labels=np.concatenate([p.labels for p in parts]),
            element=np.concatenate([p.element for p in parts]),
            tex=np.concatenate([p.tex for p in parts]),
            uv_affine=np.concatenate([p.uv_affine for p in parts]),
            tint_bgr=np.concatenate([p.tint_bgr for p in parts]),
            macro=np.concatenate([p.macro for p in parts]),
        )

    def triangle_normals(self) -> np.ndarray:
        v = self.vertices[self.triangles]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    def transformed(self, T: np.ndarray) -> "Mesh":
        """The mesh with vertices mapped by a 4x4 rigid transform (texture follows the surface)."""
        v = self.vertices @ T[:3, :3].T + T[:3, 3]
        Tinv = np.linalg.inv(T)
        return replace(self, vertices=v, uv_affine=(self.uv_affine.astype(np.float64) @ Tinv).astype(np.float32))


def _part(verts, tris, label, tex, uvA, tint, elem=-1, macro=False) -> Mesh:
    tris = np.asarray(tris, np.int32).reshape(-1, 3)
    n = len(tris)
    uvA = np.asarray(uvA, np.float32)
    if uvA.ndim == 2:
        uvA = np.broadcast_to(uvA, (n, 2, 4))
    return Mesh(
        vertices=np.asarray(verts, float).reshape(-1, 3), triangles=tris,
        labels=np.full(n, label, np.uint8), element=np.full(n, elem, np.int32),
        tex=np.full(n, tex, np.int16), uv_affine=np.ascontiguousarray(uvA),
        tint_bgr=np.broadcast_to(np.asarray(tint, np.float32), (n, 3)).copy(),
        macro=np.full(n, macro, bool),
    )


def _uv_plane(angle_rad: float, texel_m: float, offset_px, texel_v_m: float | None = None) -> np.ndarray:
    """Horizontal planar mapping rotated by angle: u along (cos, sin), v along (−sin, cos)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    tv = texel_v_m or texel_m
    return np.array([[c / texel_m, s / texel_m, 0, offset_px[0]], [-s / tv, c / tv, 0, offset_px[1]]])


def _uv_wall(p0, p1, texel_m: float, offset_px) -> np.ndarray:
    d = (np.asarray(p1) - np.asarray(p0)) / max(np.linalg.norm(np.asarray(p1) - np.asarray(p0)), 1e-9)
    # u along the wall (continuous around corners via the projection of x,y), v downwards
    return np.array([[d[0] / texel_m, d[1] / texel_m, 0, offset_px[0]], [0, 0, -1 / texel_m, offset_px[1]]])


def _uv_by_normal(verts: np.ndarray, tris: np.ndarray, texel_m: float, rng) -> np.ndarray:
    """Per-triangle planar mapping for small objects: horizontal if facing up, else along the wall."""
    v = verts[tris]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    out = np.empty((len(tris), 2, 4))
    off = rng.uniform(0, TILE_PX, 2)
    for i, (ni, vi) in enumerate(zip(n, v)):
        if abs(ni[2]) > 0.7 * np.linalg.norm(ni):
            out[i] = _uv_plane(0.0, texel_m, off)
        else:
            h = np.array([-ni[1], ni[0]])
            out[i] = _uv_wall(vi[0, :2], vi[0, :2] + h, texel_m, off)
    return out


def _orient_outward(verts: np.ndarray, tris: np.ndarray, centre: np.ndarray) -> np.ndarray:
    v = verts[tris]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    flip = np.einsum("ij,ij->i", n, v.mean(axis=1) - centre) < 0
    tris = tris.copy()
    tris[flip] = tris[flip][:, ::-1]
    return tris


# --------------------------------------------------------------------------- layout
def _make_terrain(spec: WorldSpec, rng) -> Terrain:
    k = 4
    wl = rng.uniform(250, 900, k)
    ang = rng.uniform(0, 2 * np.pi, k)
    kvec = np.stack([np.cos(ang), np.sin(ang)], 1) * (2 * np.pi / wl)[:, None]
    amp = rng.uniform(0.5, 1.0, k)
    amp = amp / amp.sum() * spec.relief_m
    return Terrain(amp, kvec, rng.uniform(0, 2 * np.pi, k), spec.extent_m, spec.terrain_step_m)


def _footprint(kind: str, rng) -> tuple[np.ndarray, tuple]:
    """Footprint centred at 0 (CCW outline, convex parts)."""
    if kind == "rect":
        w, d = rng.uniform(12, 34), rng.uniform(12, 34)
        o = np.array([[-w / 2, -d / 2], [w / 2, -d / 2], [w / 2, d / 2], [-w / 2, d / 2]])
        return o, (o,)
    if kind == "L":
        w, d = rng.uniform(22, 36), rng.uniform(22, 36)
        a, b = rng.uniform(0.35, 0.6) * w, rng.uniform(0.35, 0.6) * d
        x0, y0 = -w / 2, -d / 2
        o = np.array([[x0, y0], [x0 + w, y0], [x0 + w, y0 + b], [x0 + a, y0 + b], [x0 + a, y0 + d], [x0, y0 + d]])
        p1 = np.array([[x0, y0], [x0 + w, y0], [x0 + w, y0 + b], [x0, y0 + b]])
        p2 = np.array([[x0, y0 + b], [x0 + a, y0 + b], [x0 + a, y0 + d], [x0, y0 + d]])
        return o, (p1, p2)
    if kind == "polygon":
        n = int(rng.choice([5, 6, 8, 12]))
        r = rng.uniform(8, 16)
        t = np.arange(n) * 2 * np.pi / n + rng.uniform(0, np.pi)
        o = np.stack([r * np.cos(t), r * np.sin(t)], 1)
        return o, (o,)
    # quad: a convex trapezoid / parallelogram
    w, d = rng.uniform(14, 32), rng.uniform(12, 28)
    s1, s2 = rng.uniform(-6, 6, 2)
    o = np.array([[-w / 2, -d / 2], [w / 2, -d / 2], [w / 2 + s1, d / 2], [-w / 2 + s2, d / 2]])
    return o, (o,)


def _rot2(a: float) -> np.ndarray:
    return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


def _place_buildings(spec: WorldSpec, terrain: Terrain, grid_angle: float, n_side: int, rng) -> list[Building]:
    B = spec.block_m
    half = n_side * B / 2
    R = _rot2(grid_angle)
    blocks = [(i, j) for i in range(n_side) for j in range(n_side)]
    placed: list[tuple[np.ndarray, float]] = []  # (centre, radius) in grid coords
    out: list[Building] = []
    kinds = ["rect", "L", "polygon", "quad"]
    attempts = 0
    while len(out) < spec.n_buildings and attempts < spec.n_buildings * 200:
        attempts += 1
        i, j = blocks[rng.integers(len(blocks))]
        kind = kinds[rng.choice(4, p=[0.4, 0.25, 0.15, 0.2])]
        fp, parts = _footprint(kind, rng)
        yaw = rng.choice([0.0, np.pi / 2]) + rng.normal(0, 0.05)
        r = float(np.max(np.linalg.norm(fp, axis=1)))
        lo = -half + i * B + _ROAD_WIDTH_M / 2 + 3 + r
        hi = -half + (i + 1) * B - _ROAD_WIDTH_M / 2 - 3 - r
        lo2 = -half + j * B + _ROAD_WIDTH_M / 2 + 3 + r
        hi2 = -half + (j + 1) * B - _ROAD_WIDTH_M / 2 - 3 - r
        if hi <= lo or hi2 <= lo2:
            continue
        c = np.array([rng.uniform(lo, hi), rng.uniform(lo2, hi2)])
        if any(np.linalg.norm(c - pc) < r + pr + 4 for pc, pr in placed):
            continue
        placed.append((c, r))
        Rb = R @ _rot2(yaw)
        to_enu = lambda p, Rb=Rb, c=c: p @ Rb.T + R @ c  # noqa: E731
        outline = to_enu(fp)
        gz = float(terrain.height(outline[:, 0], outline[:, 1]).min())
        u = rng.random()
        h = spec.min_height_m + (spec.max_height_m - spec.min_height_m) * (u ** 2.2)  # many low, few towers
        out.append(Building(
            id=len(out), kind=kind, outline_enu=outline, parts=tuple(to_enu(p) for p in parts),
            ground_z_m=gz, height_m=float(h),
            facade_tex=int(rng.choice([Tex.FACADE_A, Tex.FACADE_B, Tex.FACADE_C])),
            roof_tex=int(rng.choice([Tex.ROOF_A, Tex.ROOF_B, Tex.ROOF_C])),
        ))
    return out


def _inside_any(xy: np.ndarray, buildings: list[Building], margin_m: float) -> bool:
    for b in buildings:
        c = b.outline_enu.mean(0)
        if np.linalg.norm(xy - c) < np.max(np.linalg.norm(b.outline_enu - c, axis=1)) + margin_m:
            return True
    return False


# --------------------------------------------------------------------------- meshing
def terrain_mesh(terrain: Terrain, rng) -> Mesh:
    n = int(round(terrain.extent_m / terrain.step_m)) + 1
    xs = np.linspace(-terrain.extent_m / 2, terrain.extent_m / 2, n)
    X, Y = np.meshgrid(xs, xs)
    V = np.stack([X.ravel(), Y.ravel(), terrain.height(X, Y).ravel()], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    # land-use patches (~50 m): grass, soil, gravel, paving, each with its own tint and offset
    patch = 50.0
    cent = V[tris].mean(1)
    pid = np.floor(cent[:, 0] / patch).astype(int) * 7919 + np.floor(cent[:, 1] / patch).astype(int)
    uniq, inv = np.unique(pid, return_inverse=True)
    choice = rng.choice(4, size=len(uniq), p=[0.55, 0.2, 0.15, 0.1])
    slots = np.array([Tex.GRASS, Tex.SOIL, Tex.GRAVEL, Tex.PAVING])[choice]
    tints = np.array([[0.55, 0.85, 0.6], [0.6, 0.75, 0.85], [0.85, 0.85, 0.85], [0.8, 0.8, 0.8]])[choice]
    tints = tints * rng.uniform(0.85, 1.15, (len(uniq), 1))
    offs = rng.uniform(0, TILE_PX, (len(uniq), 2))
    angs = rng.uniform(0, 2 * np.pi, len(uniq))
    uv = np.stack([_uv_plane(a_, _TEXEL_GROUND_M, o) for a_, o in zip(angs, offs)])
    m = _part(V, tris, GROUND, 0, uv[inv], [1, 1, 1], macro=True)
    m.tex[:] = slots[inv]
    m.tint_bgr[:] = tints[inv]
    return m


def road_mesh(road: Road, terrain: Terrain, step_m: float) -> Mesh:
    d = road.b_enu - road.a_enu
    L = float(np.linalg.norm(d))
    d = d / L
    nrm = np.array([-d[1], d[0]])
    s = np.linspace(0, L, max(2, int(L / step_m) + 1))
    c = road.a_enu + s[:, None] * d
    left, right = c + nrm * road.width_m / 2, c - nrm * road.width_m / 2
    zl = terrain.height(left[:, 0], left[:, 1]) + road.z_offset_m
    zr = terrain.height(right[:, 0], right[:, 1]) + road.z_offset_m
    V = np.concatenate([np.c_[right, zr], np.c_[left, zl]])
    k = len(s)
    i = np.arange(k - 1)
    tris = np.concatenate([np.stack([i, i + 1, k + i + 1], 1), np.stack([i, k + i + 1, k + i], 1)])
    ang = math.atan2(d[1], d[0])
    # v = cross-road distance mapped to half a tile (centre line at TILE/4, the un-mirrored half)
    tv = road.width_m / (TILE_PX / 2)
    A = _uv_plane(ang, 0.1, (0, 0), tv)
    A[1, 3] = -(A[1, :2] @ road.a_enu) + TILE_PX / 4
    A[0, 3] = -(A[0, :2] @ road.a_enu)
    return _part(V, tris, ROAD, Tex.ROAD, A, [0.95, 0.95, 0.95], macro=True)


def building_mesh(b: Building, rng) -> Mesh:
    sink = 1.0
    z0, z1 = b.ground_z_m - sink, b.roof_z_m
    o = b.outline_enu
    n = len(o)
    parts = []
    off = rng.uniform(0, TILE_PX, 2)
    tint = rng.uniform(0.75, 1.15, 3) * np.array([0.95, 0.97, 1.0])
    perim = 0.0
    for i in range(n):
        p0, p1 = o[i], o[(i + 1) % n]
        V = [[*p0, z0], [*p1, z0], [*p1, z1], [*p0, z1]]
        A = _uv_wall(p0, p1, _TEXEL_FACADE_M, (0, 0))
        # continuous u around the building, v = 0 at the roof line (windows align with storeys)
        A[0, 3] = perim / _TEXEL_FACADE_M - A[0, :2] @ p0 + off[0]
        A[1, 3] = z1 / _TEXEL_FACADE_M
        perim += float(np.linalg.norm(p1 - p0))
        parts.append(_part(V, [[0, 1, 2], [0, 2, 3]], BUILDING, b.facade_tex, A, tint, b.id))
    roof_tint = rng.uniform(0.7, 1.2) * rng.uniform(0.85, 1.1, 3)
    A = _uv_plane(rng.uniform(0, np.pi), _TEXEL_ROOF_M, rng.uniform(0, TILE_PX, 2))
    for p in b.parts:
        m = len(p)
        V = np.c_[p, np.full(m, z1)]
        tris = [[0, k, k + 1] for k in range(1, m - 1)]
        parts.append(_part(V, tris, BUILDING, b.roof_tex, A, roof_tint, b.id))
    return Mesh.concat(parts)


def tree_mesh(t: Tree, terrain: Terrain, rng) -> Mesh:
    """Low-poly crown (octagonal bicone) on the ground — vegetation the GIS model lacks."""
    k = 8
    z = float(terrain.height(t.xy_enu[0], t.xy_enu[1]))
    a = np.arange(k) * 2 * np.pi / k + rng.uniform(0, 1)
    zr = z + t.height_m * 0.45
    ring = np.c_[t.xy_enu + t.radius_m * np.stack([np.cos(a), np.sin(a)], 1) * rng.uniform(0.8, 1.2, (k, 1)), np.full(k, zr)]
    V = np.vstack([ring, [*t.xy_enu, z + t.height_m], [*t.xy_enu, z + 0.5]])
    i = np.arange(k)
    tris = np.concatenate([np.stack([i, (i + 1) % k, np.full(k, k)], 1), np.stack([(i + 1) % k, i, np.full(k, k + 1)], 1)])
    tris = _orient_outward(V, tris, np.array([*t.xy_enu, zr]))
    tint = np.array([0.35, 0.75, 0.45]) * rng.uniform(0.7, 1.2)
    return _part(V, tris, VEGETATION, Tex.FOLIAGE, _uv_by_normal(V, tris, 0.03, rng), tint)


def car_mesh(c: Car, terrain: Terrain, rng) -> Mesh:
    L, W, H = 4.5, 1.9, 1.5
    z = float(terrain.height(c.xy_enu[0], c.xy_enu[1])) + 0.2
    corners = np.array([[x, y] for x, y in [(-L / 2, -W / 2), (L / 2, -W / 2), (L / 2, W / 2), (-L / 2, W / 2)]]) @ _rot2(c.yaw_rad).T + c.xy_enu
    V = np.vstack([np.c_[corners, np.full(4, z)], np.c_[corners, np.full(4, z + H)]])
    tris = np.array([[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
                     [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    tris = _orient_outward(V, tris, V.mean(0))
    tint = rng.choice([[0.3, 0.3, 1.2], [1.2, 0.6, 0.3], [1.3, 1.3, 1.3], [0.4, 0.4, 0.45], [0.3, 1.0, 1.2]])
    return _part(V, tris, CLUTTER, Tex.CLUTTER, _uv_by_normal(V, tris, 0.01, rng), tint)


# --------------------------------------------------------------------------- world
@dataclass
class World:
    """A site: its description (for GIS export and stale variants) and its render mesh."""

    spec: WorldSpec
    seed: int
    origin: LocalFrame
    terrain: Terrain
    roads: list[Road]
    buildings: list[Building]
    trees: list[Tree]
    cars: list[Car]
    site_half_m: float
    #: 4x4 ENU→ENU transform applied to this description's geometry (identity for the true world;
    #: the geo-registration error for a GIS model variant)
    T_model_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    textures: Textures | None = None

    @functools.cached_property
    def mesh(self) -> Mesh:
        rng = np.random.default_rng(self.seed + 1)
        parts = [terrain_mesh(self.terrain, rng)]
        parts += [road_mesh(r, self.terrain, self.terrain.step_m) for r in self.roads]
        parts += [building_mesh(b, rng) for b in self.buildings]
        parts += [tree_mesh(t, self.terrain, rng) for t in self.trees]
        parts += [car_mesh(c, self.terrain, rng) for c in self.cars]
        m = Mesh.concat(parts)
        return m if np.allclose(self.T_model_world, np.eye(4)) else m.transformed(self.T_model_world)

    def building(self, bid: int) -> Building:
        return next(b for b in self.buildings if b.id == bid)

    def ground_height_m(self, x, y) -> np.ndarray:
        """Terrain height (ENU up, metres) of the true relief at ENU (x, y)."""
        return self.terrain.height(x, y)

    def mesh_o3d(self):
        """(open3d.geometry.TriangleMesh in ENU, per-triangle ASPRS labels)."""
        import open3d as o3d

        m = self.mesh
        om = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(m.vertices), o3d.utility.Vector3iVector(m.triangles))
        om.compute_triangle_normals()
        return om, m.labels.copy()

    def gis_points_enu(self, spacing_m: float = 1.0, labels=(GROUND, BUILDING, ROAD), seed: int = 0,
                          max_points: int = 2_000_000) -> tuple[np.ndarray, np.ndarray]:
        """Area-uniform surface samples (about one per spacing_m²) of triangles with the given labels,
        within the terrain extent: (points (N, 3) ENU, labels (N,) uint8)."""
        m = self.mesh
        keep = np.isin(m.labels, np.asarray(labels))
        v = m.vertices[m.triangles[keep]]
        area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
        n = int(min(max_points, area.sum() / spacing_m ** 2))
        rng = np.random.default_rng(seed)
        tri = rng.choice(len(v), size=n, p=area / area.sum())
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        w = np.stack([1 - s, s * (1 - r2), s * r2], 1)
        pts = np.einsum("nk,nkj->nj", w, v[tri])
        return pts, m.labels[keep][tri]


def make_world(spec: WorldSpec = WorldSpec(), seed: int = 0, with_textures: bool = True) -> World:
    rng = np.random.default_rng(seed)
    terrain = _make_terrain(spec, rng)
    n_side = max(2, math.ceil(math.sqrt(spec.n_buildings / 2.5)))
    grid_angle = float(rng.uniform(-0.35, 0.35))
    buildings = _place_buildings(spec, terrain, grid_angle, n_side, rng)
    R = _rot2(grid_angle)
    half_grid = n_side * spec.block_m / 2
    ext = spec.extent_m / 2 - 20
    roads = []
    for k in range(n_side + 1):
        c = -half_grid + k * spec.block_m
        roads.append(Road(R @ [c, -ext], R @ [c, ext], _ROAD_WIDTH_M, 0.20))
        roads.append(Road(R @ [-ext, c], R @ [ext, c], _ROAD_WIDTH_M, 0.25))
    trees, cars = [], []
    n_trees = int(spec.trees_per_building * spec.n_buildings)
    while len(trees) < n_trees:
        xy = R @ rng.uniform(-half_grid - 40, half_grid + 40, 2)
        g = np.linalg.inv(R) @ xy
        on_road = np.min(np.abs(((g + half_grid + spec.block_m / 2) % spec.block_m) - spec.block_m / 2)) < _ROAD_WIDTH_M / 2 + 2
        if on_road or _inside_any(xy, buildings, 3.0):
            continue
        trees.append(Tree(xy, float(rng.uniform(2.0, 4.5)), float(rng.uniform(5, 14))))
    for _ in range(int(spec.cars_per_building * spec.n_buildings)):
        k = rng.integers(n_side + 1)
        along = rng.uniform(-half_grid - 40, half_grid + 40)
        lane = rng.choice([-2.5, 2.5])
        c = -half_grid + k * spec.block_m + lane
        if rng.random() < 0.5:
            cars.append(Car(R @ [c, along], grid_angle + np.pi / 2))
        else:
            cars.append(Car(R @ [along, c], grid_angle))
    return World(
        spec=spec, seed=seed, origin=LocalFrame(spec.lat0_deg, spec.lon0_deg, spec.h0_ellipsoid_m),
        terrain=terrain, roads=roads, buildings=buildings, trees=trees, cars=cars, site_half_m=half_grid,
        textures=make_textures(seed) if with_textures else None,
    )
