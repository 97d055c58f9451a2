"""Stale GIS variants: the model differs from the rendered world like TerraSLAM's F-A/F-B sites
(§7.4.3: changed building contours; new buildings and renovations missing), plus a global
geo-registration error of the model, as real GIS models have.

The GIS model never contains vegetation or clutter (cars) — real building/terrain models do not.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from companion.sim.world import Building, World, _footprint, _inside_any


@dataclass(frozen=True)
class StaleSpec:
    """What the GIS model gets wrong. Fractions of the world's buildings; distances in metres."""

    changed_frac: float = 0.0       # outline moved / resized, height changed
    change_m: float = 2.0           # outline shift of a changed building
    height_change_frac: float = 0.2  # relative height change of a changed building
    n_new: int = 0                  # real buildings the model lacks (built after the survey)
    n_demolished: int = 0           # model buildings that no longer exist
    registration_error_m: float = 0.0   # global horizontal offset of the model
    registration_yaw_deg: float = 0.0   # global rotation of the model about the origin

    def __post_init__(self):
        if not 0 <= self.changed_frac <= 1:
            raise ValueError(f"StaleSpec.changed_frac must be in [0, 1], got {self.changed_frac}")
        if self.registration_error_m < 0 or self.change_m < 0:
            raise ValueError("StaleSpec distances must be >= 0")


#: presets named after the paper's sites: F-A moderately outdated, F-B significantly outdated
STALE_PRESETS = {
    "fresh": StaleSpec(),
    "F-A": StaleSpec(changed_frac=0.15, change_m=1.5, n_new=1, n_demolished=0, registration_error_m=0.2, registration_yaw_deg=0.05),
    "F-B": StaleSpec(changed_frac=0.3, change_m=3.0, n_new=3, n_demolished=2, registration_error_m=0.4, registration_yaw_deg=0.1),
}


@dataclass(frozen=True)
class StaleReport:
    """What was changed (ids refer to the world's buildings; demolished ids are new ids ≥ 10000)."""

    changed_ids: tuple[int, ...]
    shift_enu_m: dict
    missing_ids: tuple[int, ...]
    demolished_ids: tuple[int, ...]
    T_model_world: np.ndarray


def registration_transform(spec: StaleSpec, rng) -> np.ndarray:
    b = rng.uniform(0, 2 * np.pi)
    yaw = math.radians(spec.registration_yaw_deg) * rng.choice([-1, 1])
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:3, 3] = [spec.registration_error_m * math.sin(b), spec.registration_error_m * math.cos(b),
                0.5 * spec.registration_error_m * rng.choice([-1, 1])]
    return T


def stale_variant(world: World, spec: StaleSpec, seed: int = 0) -> tuple[World, StaleReport]:
    """The GIS model's view of ``world`` (buildings, terrain, roads only), stale per ``spec``."""
    rng = np.random.default_rng(seed + 7919)
    ids = [b.id for b in world.buildings]
    order = rng.permutation(ids)
    missing = tuple(int(i) for i in order[:spec.n_new])
    n_changed = int(round(spec.changed_frac * len(ids)))
    changed = tuple(int(i) for i in order[spec.n_new:spec.n_new + n_changed])
    shifts = {}
    out: list[Building] = []
    for b in world.buildings:
        if b.id in missing:
            continue
        if b.id in changed:
            ang = rng.uniform(0, 2 * np.pi)
            d = spec.change_m * np.array([math.cos(ang), math.sin(ang)])
            shifts[b.id] = d
            dh = b.height_m * spec.height_change_frac * rng.choice([-1, 1])
            b = replace(b, outline_enu=b.outline_enu + d, parts=tuple(p + d for p in b.parts),
                        height_m=max(3.0, b.height_m + dh))
        out.append(b)
    demolished = []
    tries = 0
    while len(demolished) < spec.n_demolished and tries < 500:
        tries += 1
        c = rng.uniform(-world.site_half_m, world.site_half_m, 2)
        fp, parts = _footprint("rect", rng)
        if _inside_any(c, world.buildings + out, 25.0):
            continue
        bid = 10000 + len(demolished)
        gz = float(world.terrain.height(*(fp + c).T).min())
        b = Building(bid, "rect", fp + c, tuple(p + c for p in parts), gz, float(rng.uniform(8, 20)),
                     world.buildings[0].facade_tex, world.buildings[0].roof_tex)
        out.append(b)
        demolished.append(bid)
    T = registration_transform(spec, rng)
    gis = replace(world, buildings=out, trees=[], cars=[], T_model_world=T)
    gis.__dict__.pop("mesh", None)  # never share the world's cached mesh
    return gis, StaleReport(changed, shifts, missing, tuple(demolished), T)
