"""Named scenarios and the live API: world + flight + camera + GNSS + autopilot signals.

``make_scenario("nominal", seed=0, n_frames=60).steps()`` yields SimStep values frame by frame
(render on demand, nothing written to disk). The same Scenario is what ``write_dataset`` stores.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace
from typing import Iterator

import numpy as np

from companion.sim.autopilot_signals import AttitudeNoise, simulate_attitude
from companion.sim.flight import FlightSpec, Trajectory, make_trajectory
from companion.sim.gnss import GnssEvent, GnssSpec, simulate_gnss
from companion.sim.render import Lighting, Renderer
from companion.sim.stale import STALE_PRESETS, StaleReport, StaleSpec, stale_variant
from companion.sim.types import AttitudeSample, SimStep, TruthPose
from companion.sim.world import World, WorldSpec, make_world
from gis.geodesy import LocalFrame, ellipsoid_to_msl
from mavlink_bridge.types import GnssSample
from slam.types import CameraModel, Frame


@dataclass(frozen=True)
class ScenarioSpec:
    """Everything that defines a simulated flight. Angles in degrees, camera pitch below the body's
    forward axis (0 forward, 90 nadir)."""

    name: str
    world: WorldSpec = WorldSpec()
    flight: FlightSpec = FlightSpec()
    width_px: int = 640
    height_px: int = 480
    hfov_deg: float = 65.0
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    camera_pitch_deg: float = 40.0
    fps: float = 30.0
    lighting: str = "normal"
    motion_blur: bool = False
    exposure_s: float = 1 / 120
    gnss: GnssSpec = GnssSpec()
    gnss_antenna_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # the receiver's antenna from the body origin, FRD m
    attitude: AttitudeNoise = AttitudeNoise()
    stale: StaleSpec = StaleSpec()
    max_duration_s: float | None = None

    def __post_init__(self):
        if not 0 <= self.camera_pitch_deg <= 90:
            raise ValueError(f"camera_pitch_deg must be in [0, 90], got {self.camera_pitch_deg}")
        if not 1 <= self.fps <= 120:
            raise ValueError(f"fps must be in [1, 120], got {self.fps}")


_LOOP = FlightSpec(kind="loop", speed_mps=7.0, altitude_m=80.0, size_m=200.0, laps=1.25)
SCENARIOS: dict[str, ScenarioSpec] = {
    "nominal": ScenarioSpec("nominal", flight=_LOOP),
    "stale": ScenarioSpec("stale", flight=_LOOP, stale=STALE_PRESETS["F-B"]),
    "dark": ScenarioSpec("dark", flight=_LOOP, lighting="dark"),
    "bright": ScenarioSpec("bright", flight=_LOOP, lighting="bright"),
    "fast": ScenarioSpec("fast", flight=replace(_LOOP, speed_mps=13.0, a_max_mps2=3.0, a_lat_max_mps2=4.0, laps=1.5),
                         motion_blur=True, exposure_s=1 / 30),
    "slow": ScenarioSpec("slow", flight=replace(_LOOP, speed_mps=3.5)),
    "loop": ScenarioSpec("loop", flight=replace(_LOOP, laps=2.25, speed_mps=6.0)),
    # the GIS model 3 m off its georeference (OSM-grade), on the long `loop` flight: gis/align/georef.py
    "offset": ScenarioSpec("offset", flight=replace(_LOOP, laps=2.25, speed_mps=6.0), stale=StaleSpec(registration_error_m=3.0)),
    "survey": ScenarioSpec("survey", flight=FlightSpec(kind="survey", speed_mps=8.0, altitude_m=110.0, size_m=240.0,
                                                        row_spacing_m=80.0), camera_pitch_deg=70.0),
    "orbit": ScenarioSpec("orbit", flight=FlightSpec(kind="orbit", speed_mps=5.0, altitude_m=70.0, size_m=160.0, laps=1.0)),
    "nadir": ScenarioSpec("nadir", flight=replace(_LOOP, altitude_m=100.0), camera_pitch_deg=90.0),
    "distorted": ScenarioSpec("distorted", flight=_LOOP, dist=(-0.12, 0.03, 0.0, 0.0, 0.0)),
    "dgps": ScenarioSpec("dgps", flight=_LOOP, gnss=GnssSpec(base="dgps")),
    "urban": ScenarioSpec("urban", flight=replace(_LOOP, altitude_m=35.0, speed_mps=5.0), camera_pitch_deg=30.0,
                          gnss=GnssSpec(base="urban")),
    "gnss_loss": ScenarioSpec("gnss_loss", flight=_LOOP, gnss=GnssSpec(events=(GnssEvent("dropout", 30.0),))),
    "jamming": ScenarioSpec("jamming", flight=_LOOP, gnss=GnssSpec(events=(GnssEvent("jamming", 25.0),))),
    "spoof": ScenarioSpec("spoof", flight=_LOOP, gnss=GnssSpec(events=(GnssEvent("spoof_drift", 30.0, drift_mps=1.0),))),
}


def T_body_cam_pitched(pitch_down_deg: float) -> np.ndarray:
    """Camera (OpenCV) → body (FRD) for a camera looking forward and pitched down (90: nadir,
    image top towards the nose)."""
    th = math.radians(pitch_down_deg)
    z = [math.cos(th), 0.0, math.sin(th)]
    x = [0.0, 1.0, 0.0]
    y = [-math.sin(th), 0.0, math.cos(th)]
    T = np.eye(4)
    T[:3, :3] = np.array([x, y, z]).T
    return T


def camera_from_spec(spec: ScenarioSpec) -> CameraModel:
    f = spec.width_px / 2 / math.tan(math.radians(spec.hfov_deg) / 2)
    K = np.array([[f, 0, (spec.width_px - 1) / 2], [0, f, (spec.height_px - 1) / 2], [0, 0, 1.0]])
    return CameraModel(spec.width_px, spec.height_px, K, np.asarray(spec.dist, float))


@dataclass
class Truth:
    """Truth arrays for all frames (vectorised once)."""

    t_s: np.ndarray
    T_enu_body: np.ndarray
    T_enu_cam: np.ndarray
    v_enu: np.ndarray
    p_ecef: np.ndarray          # camera centres
    lat: np.ndarray             # lat / lon / h_ell / h_msl / p_body_ecef: the body origin (what a fix
    lon: np.ndarray             # reports, truth.csv's position)
    h_ell: np.ndarray
    h_msl: np.ndarray
    p_body_ecef: np.ndarray

    def pose(self, i: int) -> TruthPose:
        return TruthPose(float(self.t_s[i]), i, self.T_enu_cam[i], self.T_enu_body[i], self.p_ecef[i],
                         float(self.lat[i]), float(self.lon[i]), float(self.h_ell[i]), float(self.h_msl[i]), self.v_enu[i],
                         self.p_body_ecef[i])


@dataclass
class Scenario:
    spec: ScenarioSpec
    seed: int
    world: World
    trajectory: Trajectory
    camera: CameraModel
    T_body_cam: np.ndarray
    n_frames: int
    truth: Truth
    gnss_samples: list[GnssSample]
    attitude_samples: list[AttitudeSample]
    lighting: Lighting
    _renderer: Renderer | None = field(default=None, repr=False)

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def origin(self) -> LocalFrame:
        return self.world.origin

    @property
    def fps(self) -> float:
        return self.spec.fps

    @property
    def duration_s(self) -> float:
        return self.n_frames / self.spec.fps

    @functools.cached_property
    def gis(self) -> tuple[World, StaleReport]:
        """The GIS model's view of the world (stale per spec) and what differs."""
        return stale_variant(self.world, self.spec.stale, self.seed)

    @property
    def renderer(self) -> Renderer:
        if self._renderer is None:
            self._renderer = Renderer(self.world.mesh, self.world.textures, self.camera,
                                      Lighting.named(self.spec.lighting), seed=self.seed)
        return self._renderer

    def render(self, i: int):
        """RenderOutput of frame i (image, depth, hit points, labels)."""
        T = self.truth.T_enu_cam[i]
        return self.renderer.render(T, self._motion_px(i) if self.spec.motion_blur else None)

    def _motion_px(self, i: int) -> tuple[float, float]:
        """Image motion of the scene point at the principal ray during the exposure."""
        T = self.truth.T_enu_cam[i]
        t, _, d, _ = self.renderer.cast_one(T, np.array([0.0, 0.0, 1.0]))
        if not np.isfinite(t):
            return (0.0, 0.0)
        p = T[:3, 3] + d * t
        p0, _, _, R = self.trajectory.state(self.truth.t_s[i] - self.spec.exposure_s)
        Rc = R[0] @ self.T_body_cam[:3, :3]
        pc = Rc.T @ (p - p0[0])
        return (self.camera.fx * pc[0] / pc[2], self.camera.fy * pc[1] / pc[2])

    def steps(self, start: int = 0) -> Iterator[SimStep]:
        gi = ai = 0
        g, a = self.gnss_samples, self.attitude_samples
        for i in range(start, self.n_frames):
            t = self.truth.t_s[i]
            out = self.render(i)
            g0 = gi
            while gi < len(g) and g[gi].t_s <= t:
                gi += 1
            a0 = ai
            while ai < len(a) and a[ai].t_s <= t:
                ai += 1
            yield SimStep(Frame(out.image_bgr, float(t), i), self.truth.pose(i), g[g0:gi], a[a0:ai])


def make_truth(traj: Trajectory, origin: LocalFrame, T_body_cam: np.ndarray, t_s: np.ndarray) -> Truth:
    p, v, _, R = traj.state(t_s)
    n = len(t_s)
    T_enu_body = np.tile(np.eye(4), (n, 1, 1))
    T_enu_body[:, :3, :3] = R
    T_enu_body[:, :3, 3] = p
    T_enu_cam = T_enu_body @ T_body_cam
    p_ecef = origin.enu_to_ecef(T_enu_cam[:, :3, 3])
    lat, lon, h = origin.enu_to_geodetic(p)
    return Truth(t_s, T_enu_body, T_enu_cam, v, p_ecef, lat, lon, h, ellipsoid_to_msl(lat, lon, h), origin.enu_to_ecef(p))


def scenario_spec(name: str, **overrides) -> ScenarioSpec:
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; choose one of {', '.join(SCENARIOS)}")
    return replace(SCENARIOS[name], **overrides) if overrides else SCENARIOS[name]


def make_scenario(name: str = "nominal", seed: int = 0, n_frames: int | None = None,
                  spec: ScenarioSpec | None = None, **overrides) -> Scenario:
    """Build a scenario (world, flight, truth, GNSS and attitude logs); frames render lazily.

    n_frames: number of camera frames (default: the whole flight); more than the flight lasts is
    an error. ``overrides`` replace ScenarioSpec fields, e.g. ``gnss=GnssSpec(...)``.
    """
    spec = spec or scenario_spec(name, **overrides)
    world = make_world(spec.world, seed)
    flight = spec.flight
    if flight.kind == "orbit" and flight.look_at is None:  # orbit the tallest building, looking at it
        b = max(world.buildings, key=lambda b: b.height_m)
        c = b.outline_enu.mean(0)
        flight = replace(flight, center_enu=(float(c[0]), float(c[1])), look_at=(float(c[0]), float(c[1]), b.roof_z_m * 0.6))
    traj = make_trajectory(flight)
    full = int(math.floor(traj.duration_s * spec.fps)) + 1
    if spec.max_duration_s is not None:
        full = min(full, int(spec.max_duration_s * spec.fps))
    if n_frames is None:
        n_frames = full
    if not 1 <= n_frames <= full:
        raise ValueError(f"n_frames must be in [1, {full}] for scenario {spec.name!r} ({traj.duration_s:.0f} s at {spec.fps} fps), got {n_frames}")
    origin = world.origin
    T_body_cam = T_body_cam_pitched(spec.camera_pitch_deg)
    t_frames = np.arange(n_frames) / spec.fps
    truth = make_truth(traj, origin, T_body_cam, t_frames)
    t_end = t_frames[-1]
    tg = np.arange(0, t_end + 1e-9, 1 / spec.gnss.rate_hz)
    pg, vg, _, Rg = traj.state(tg)
    h_agl = pg[:, 2] - world.ground_height_m(pg[:, 0], pg[:, 1])
    antenna = pg + Rg @ np.asarray(spec.gnss_antenna_m, float)  # the receiver solves for its antenna
    gnss = simulate_gnss(spec.gnss, origin, tg, antenna, vg, h_agl, seed=seed + 1)
    ta = np.arange(0, t_end + 1e-9, 1 / spec.attitude.rate_hz)
    pa, _, _, Ra = traj.state(ta)
    la, lo, ha = origin.enu_to_geodetic(pa)
    x0, y0 = traj.state(0.0)[0][0, :2]
    h_home = float(origin.enu_to_geodetic([x0, y0, float(world.ground_height_m(x0, y0))])[2])  # take-off point
    att = simulate_attitude(origin, ta, Ra, la, lo, ha, h_home, spec.attitude, seed=seed + 2)
    return Scenario(spec, seed, world, traj, camera_from_spec(spec), T_body_cam, n_frames, truth, gnss, att,
                    Lighting.named(spec.lighting))
