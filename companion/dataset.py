"""The dataset layout (docs/DATASET.md): written by the simulator, read by replay and benchmarks,
and assembled by hand from a real flight. Boring on purpose: YAML + CSV + PNG/JPG.

    DATASET/
      dataset.yaml          format version, name, fps, frame count, what produced it
      site.yaml             local origin + rough initial position (+ σ) + GIS model files
      camera.yaml           OpenCV calibration (image_width/height, camera_matrix, distortion_coefficients)
      mount.yaml            T_body_cam: 4x4 camera (OpenCV) → body (FRD); p_body_gnss_m: GNSS antenna (FRD m, optional)
      images/frames.csv     seq,t_s,filename   (images/000000.png ...)
      truth.csv             optional: seq,t_s,lat_deg,lon_deg,h_ellipsoid_m,h_msl_m,roll_deg,pitch_deg,yaw_deg,vn_mps,ve_mps,vd_mps
      gnss.csv              optional: t_s,fix_type,lat_deg,lon_deg,alt_msl_m,h_ellipsoid_m,eph,epv,h_acc_m,v_acc_m,satellites,vn_mps,ve_mps,vd_mps,cog_deg
      attitude.csv          optional: t_s,roll_rad,pitch_rad,yaw_rad,baro_alt_m (baro may be empty)
      gis/                  model files (PLY + .georef.json, LAS/LAZ, GeoJSON, CityJSON, ...)

Truth and attitude angles are the body FRD frame in the local NED frame at the vehicle (ZYX
yaw-pitch-roll, as autopilots report); the truth position is the body origin (WGS-84, both heights).
"""
from __future__ import annotations

import csv
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from companion.calibration import CalibrationError, read_camera_model, write_calibration
from companion.sim.autopilot_signals import R_ned_body_at_vehicle
from companion.sim.types import AttitudeSample, SimStep, TruthPose
from gis.geodesy import R_NED_ENU, LocalFrame, R_ecef_enu, geodetic_to_ecef
from mavlink_bridge.types import GnssSample, GpsFixType
from slam.types import CameraModel, Frame

FORMAT_VERSION = 1
TRUTH_COLUMNS = ("seq", "t_s", "lat_deg", "lon_deg", "h_ellipsoid_m", "h_msl_m", "roll_deg", "pitch_deg", "yaw_deg",
                 "vn_mps", "ve_mps", "vd_mps")
GNSS_COLUMNS = ("t_s", "fix_type", "lat_deg", "lon_deg", "alt_msl_m", "h_ellipsoid_m", "eph", "epv", "h_acc_m",
                "v_acc_m", "satellites", "vn_mps", "ve_mps", "vd_mps", "cog_deg")
ATTITUDE_COLUMNS = ("t_s", "roll_rad", "pitch_rad", "yaw_rad", "baro_alt_m")


class DatasetError(ValueError):
    """A dataset file is missing or malformed; the message names the file (and line/key)."""


@dataclass(frozen=True)
class RoughPosition:
    lat_deg: float
    lon_deg: float
    h_ellipsoid_m: float
    sigma_m: float


@dataclass
class Dataset:
    root: Path
    name: str
    fps: float
    camera: CameraModel
    T_body_cam: np.ndarray
    origin: LocalFrame
    rough_position: RoughPosition
    gis_files: list[Path]
    frame_t_s: np.ndarray
    frame_paths: list[Path]
    truth: list[TruthPose] | None = None
    gnss: list[GnssSample] = field(default_factory=list)
    attitude: list[AttitudeSample] = field(default_factory=list)
    meta: dict = field(default_factory=dict)
    p_body_gnss_m: np.ndarray = field(default_factory=lambda: np.zeros(3))  # GNSS antenna, FRD m from the body origin

    @property
    def n_frames(self) -> int:
        return len(self.frame_paths)

    def image(self, i: int) -> np.ndarray:
        img = cv2.imread(str(self.frame_paths[i]), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DatasetError(f"{self.frame_paths[i]}: cannot decode image")
        return img

    def steps(self, start: int = 0) -> Iterator[SimStep]:
        """Frames from disk with truth and the GNSS/attitude samples since the previous frame."""
        gt = np.array([g.t_s for g in self.gnss])
        at = np.array([a.t_s for a in self.attitude])
        for i in range(start, self.n_frames):
            t = self.frame_t_s[i]
            t_prev = self.frame_t_s[i - 1] if i > 0 else -math.inf
            g0, g1 = np.searchsorted(gt, [t_prev, t], side="right")
            a0, a1 = np.searchsorted(at, [t_prev, t], side="right")
            yield SimStep(Frame(self.image(i), float(t), i), self.truth[i] if self.truth else None,
                          self.gnss[g0:g1], self.attitude[a0:a1])


# ------------------------------------------------------------------------------------ writing
def _write_csv(path: Path, columns, rows) -> None:
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        w.writerows(rows)


def _f(x, nd: int) -> str:
    return "" if x is None else f"{x:.{nd}f}"


def gnss_row(g: GnssSample) -> list:
    """One gnss.csv row (GNSS_COLUMNS); read_dataset gives back the sample these digits hold."""
    return [_f(g.t_s, 6), int(g.fix_type), _f(g.lat_deg, 10), _f(g.lon_deg, 10), _f(g.alt_msl_m, 4), _f(g.h_ellipsoid_m, 4),
            _f(g.eph, 2), _f(g.epv, 2), _f(g.h_acc_m, 3), _f(g.v_acc_m, 3), g.satellites,
            *(["", "", ""] if g.vel_ned_mps is None else [_f(x, 3) for x in g.vel_ned_mps]), _f(g.cog_deg, 2)]


def attitude_row(a) -> list:
    """One attitude.csv row (ATTITUDE_COLUMNS) of an AttitudeSample or the bridge's VehicleAttitude
    (whose baro_alt_m is None when no barometer reading was fresh: an empty cell)."""
    return [_f(a.t_s, 6), _f(a.roll_rad, 7), _f(a.pitch_rad, 7), _f(a.yaw_rad, 7), _f(a.baro_alt_m, 3)]


def write_mount(path: Path, T_body_cam: np.ndarray, p_body_gnss_m=(0.0, 0.0, 0.0)) -> None:
    """mount.yaml: the 4x4 camera (OpenCV) → body (FRD) transform and the GNSS antenna (FRD m)."""
    path.write_text(yaml.safe_dump({"T_body_cam": np.round(np.asarray(T_body_cam, float), 12).tolist(),
                                    "p_body_gnss_m": [float(x) for x in p_body_gnss_m]}))


def truth_rows(scenario) -> list[list[str]]:
    """truth.csv rows: the body origin's position (DATASET.md), its attitude and velocity."""
    tr = scenario.truth
    R_enu_body = tr.T_enu_body[:, :3, :3]
    ypr = np.degrees(Rotation.from_matrix(R_ned_body_at_vehicle(scenario.origin, R_enu_body, tr.lat, tr.lon)).as_euler("ZYX"))
    v_ned = tr.v_enu @ R_NED_ENU.T
    return [[str(i), _f(tr.t_s[i], 6), _f(tr.lat[i], 11), _f(tr.lon[i], 11), _f(tr.h_ell[i], 5), _f(tr.h_msl[i], 5),
             _f(ypr[i, 2], 8), _f(ypr[i, 1], 8), _f(ypr[i, 0] % 360.0, 8), _f(v_ned[i, 0], 4), _f(v_ned[i, 1], 4), _f(v_ned[i, 2], 4)]
            for i in range(len(tr.t_s))]


def write_dataset(scenario, out_dir: Path | str, progress: bool = True, image_ext: str = ".png",
                  las_spacing_m: float = 1.0) -> Path:
    """Render every frame of ``scenario`` and write the full dataset (see module doc) to out_dir."""
    from companion.sim.gis_export import export_gis

    out = Path(out_dir)
    img_dir = out / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    gis_world, stale = scenario.gis
    files = export_gis(gis_world, out / "gis", las_spacing_m=las_spacing_m, seed=scenario.seed)
    (out / "gis" / "stale_truth.yaml").write_text(yaml.safe_dump({
        "note": "simulator ground truth of how the GIS model differs from the rendered world (not model input)",
        "changed_building_ids": list(stale.changed_ids), "missing_building_ids": list(stale.missing_ids),
        "demolished_building_ids": list(stale.demolished_ids),
        "outline_shift_enu_m": {int(k): [float(x) for x in v] for k, v in stale.shift_enu_m.items()},
        "T_model_world_enu": np.asarray(stale.T_model_world).tolist(), "spec": vars(scenario.spec.stale),
    }, sort_keys=False))
    o = scenario.origin
    start = scenario.truth
    rng = np.random.default_rng(scenario.seed + 11)
    rough_err = rng.normal(0, 5.0, 3)  # a rough initial position is off by metres
    lat, lon, h = o.enu_to_geodetic(scenario.truth.T_enu_body[0, :3, 3] + rough_err)
    (out / "site.yaml").write_text(yaml.safe_dump({
        "origin": {"lat_deg": o.lat0_deg, "lon_deg": o.lon0_deg, "h_ellipsoid_m": o.h0_ellipsoid_m},
        "rough_position": {"lat_deg": float(lat), "lon_deg": float(lon), "h_ellipsoid_m": float(h), "sigma_m": 10.0},
        "gis": {"files": [str(p.relative_to(out)) for p in (files.mesh_ply, files.points_laz, files.buildings_geojson)],
                "crs": files.crs},
    }, sort_keys=False))
    write_calibration(out / "camera.yaml", scenario.camera)
    write_mount(out / "mount.yaml", scenario.T_body_cam, scenario.spec.gnss_antenna_m)
    (out / "dataset.yaml").write_text(yaml.safe_dump({
        "format_version": FORMAT_VERSION, "name": scenario.name, "fps": float(scenario.fps),
        "n_frames": int(scenario.n_frames), "generator": f"terraslam sim (seed {scenario.seed})",
        "lighting": scenario.spec.lighting, "gnss_base_mode": scenario.spec.gnss.base,
        "gnss_events": [vars(e) for e in scenario.spec.gnss.events],
    }, sort_keys=False))
    _write_csv(out / "truth.csv", TRUTH_COLUMNS, truth_rows(scenario))
    _write_csv(out / "gnss.csv", GNSS_COLUMNS, [gnss_row(g) for g in scenario.gnss_samples])
    _write_csv(out / "attitude.csv", ATTITUDE_COLUMNS, [attitude_row(a) for a in scenario.attitude_samples])
    names = [f"{i:06d}{image_ext}" for i in range(scenario.n_frames)]
    _write_csv(img_dir / "frames.csv", ("seq", "t_s", "filename"),
               [[i, _f(start.t_s[i], 6), n] for i, n in enumerate(names)])
    params = [cv2.IMWRITE_PNG_COMPRESSION, 1] if image_ext == ".png" else [cv2.IMWRITE_JPEG_QUALITY, 95]
    with ThreadPoolExecutor(max_workers=1) as pool, _progress(progress, scenario) as bar:
        pending = []
        for i in range(scenario.n_frames):
            img = scenario.render(i).image_bgr
            pending.append(pool.submit(cv2.imwrite, str(img_dir / names[i]), img, params))
            if len(pending) > 8:
                pending.pop(0).result()
            bar(i + 1)
        for p in pending:
            p.result()
    return out


class _progress:
    def __init__(self, enabled: bool, scenario):
        self.enabled, self.scenario = enabled, scenario

    def __enter__(self):
        if not self.enabled:
            return lambda i: None
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        self._p = Progress(TextColumn(f"rendering {self.scenario.name}"), BarColumn(), MofNCompleteColumn(),
                           TextColumn("{task.fields[fps]} frames/s"), TimeRemainingColumn())
        self._p.__enter__()
        task = self._p.add_task("render", total=self.scenario.n_frames, fps="-")
        import time
        t0 = time.perf_counter()

        def update(i):
            self._p.update(task, completed=i, fps=f"{i / max(time.perf_counter() - t0, 1e-6):.1f}")
        return update

    def __exit__(self, *exc):
        if self.enabled:
            self._p.__exit__(*exc)


# ------------------------------------------------------------------------------------ reading
def _yaml(path: Path) -> dict:
    if not path.is_file():
        raise DatasetError(f"{path}: missing (required by the dataset layout, see docs/DATASET.md)")
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise DatasetError(f"{path}: not valid YAML: {e}") from None
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: top level must be a mapping")
    return doc


def _num(d: dict, key: str, path: Path) -> float:
    try:
        v = float(d[key])
    except KeyError:
        raise DatasetError(f"{path}: key {key!r} missing") from None
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: key {key!r} = {d[key]!r} is not a number") from None
    if not math.isfinite(v):
        raise DatasetError(f"{path}: key {key!r} = {v} is not finite")
    return v


def _read_csv(path: Path, required: tuple[str, ...], optional: tuple[str, ...] = ()) -> list[dict]:
    with path.open(newline="") as f:
        r = csv.DictReader(f)
        missing = set(required) - set(r.fieldnames or ())
        if missing:
            raise DatasetError(f"{path}: missing columns {sorted(missing)} (have {r.fieldnames})")
        rows = list(r)
    prev = -math.inf
    for line, row in enumerate(rows, start=2):
        for k in required:
            try:
                row[k] = float(row[k])
            except (TypeError, ValueError):
                raise DatasetError(f"{path}:{line}: column {k} = {row[k]!r} is not a number") from None
        for k in optional:
            row[k] = float(row[k]) if row.get(k) not in (None, "") else None
        if row["t_s"] < prev:
            raise DatasetError(f"{path}:{line}: t_s {row['t_s']} goes back in time (previous {prev})")
        prev = row["t_s"]
    return rows


def _truth_pose(row: dict, i: int, origin: LocalFrame, T_body_cam: np.ndarray) -> TruthPose:
    lat, lon, h = row["lat_deg"], row["lon_deg"], row["h_ellipsoid_m"]
    R_ned_body = Rotation.from_euler("ZYX", [row["yaw_deg"], row["pitch_deg"], row["roll_deg"]], degrees=True).as_matrix()
    R_ecef_enuveh = R_ecef_enu(lat, lon)
    R_enu_body = origin.R_ecef_enu.T @ R_ecef_enuveh @ R_NED_ENU @ R_ned_body
    p_ecef = geodetic_to_ecef(lat, lon, h)
    T_enu_body = np.eye(4)
    T_enu_body[:3, :3] = R_enu_body
    T_enu_body[:3, 3] = origin.ecef_to_enu(p_ecef)
    T_enu_cam = T_enu_body @ T_body_cam
    v_ned = np.array([row[k] if row.get(k) is not None else np.nan for k in ("vn_mps", "ve_mps", "vd_mps")])
    v_enu = origin.R_ecef_enu.T @ R_ecef_enuveh @ (R_NED_ENU @ v_ned)
    return TruthPose(row["t_s"], i, T_enu_cam, T_enu_body, origin.enu_to_ecef(T_enu_cam[:3, 3]), lat, lon, h,
                     row["h_msl_m"], v_enu, p_ecef)


def read_dataset(path: Path | str, gis_files: list[Path] | None = None) -> Dataset:
    """Read a dataset directory (layout in docs/DATASET.md); raises DatasetError naming the file.
    ``gis_files``: the GIS model files to use instead of site.yaml's (a recording moved to another
    machine names the model where the companion computer had it)."""
    root = Path(path)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset directory not found")
    meta = _yaml(root / "dataset.yaml")
    site = _yaml(root / "site.yaml")
    try:
        camera = read_camera_model(root / "camera.yaml")
    except CalibrationError as e:
        raise DatasetError(f"{root / 'camera.yaml'}: {e}") from None
    mount_path = root / "mount.yaml"
    mount = _yaml(mount_path)
    T = np.asarray(mount.get("T_body_cam"), float)
    if T.shape != (4, 4) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise DatasetError(f"{mount_path}: T_body_cam must be a 4x4 rigid transform (rotation + translation)")
    try:
        p_gnss = np.asarray(mount.get("p_body_gnss_m", [0.0, 0.0, 0.0]), float)
    except (TypeError, ValueError):
        p_gnss = np.full(1, np.nan)
    if p_gnss.shape != (3,) or not np.all(np.isfinite(p_gnss)) or np.any(np.abs(p_gnss) > 10.0):
        raise DatasetError(f"{mount_path}: p_body_gnss_m must be 3 finite numbers (FRD metres, within 10 m of the body origin)")
    sp = root / "site.yaml"
    rp = site.get("rough_position")
    if not isinstance(rp, dict):
        raise DatasetError(f"{sp}: key 'rough_position' (lat_deg, lon_deg, h_ellipsoid_m, sigma_m) missing")
    rough = RoughPosition(_num(rp, "lat_deg", sp), _num(rp, "lon_deg", sp), _num(rp, "h_ellipsoid_m", sp),
                          float(rp.get("sigma_m", 50.0)))
    og = site.get("origin") or {"lat_deg": rough.lat_deg, "lon_deg": rough.lon_deg, "h_ellipsoid_m": rough.h_ellipsoid_m}
    origin = LocalFrame(_num(og, "lat_deg", sp), _num(og, "lon_deg", sp), _num(og, "h_ellipsoid_m", sp))
    if gis_files is None:
        gis_files = [root / f for f in (site.get("gis") or {}).get("files", [])]
        for f in gis_files:
            if not f.is_file():
                raise DatasetError(f"{sp}: gis file {f} does not exist (`terraslam replay --gis-model FILE` takes it from elsewhere)")
    else:
        gis_files = [Path(f) for f in gis_files]
        for f in gis_files:
            if not f.is_file():
                raise DatasetError(f"GIS model {f} does not exist")
    fcsv = root / "images" / "frames.csv"
    if not fcsv.is_file():
        raise DatasetError(f"{fcsv}: missing (columns seq,t_s,filename)")
    frames = _read_csv(fcsv, ("t_s",))
    paths = []
    for line, r in enumerate(frames, start=2):
        p = root / "images" / (r.get("filename") or "")
        if not p.is_file():
            raise DatasetError(f"{fcsv}:{line}: image {p} does not exist")
        paths.append(p)
    t_frames = np.array([r["t_s"] for r in frames])
    if len(t_frames) > 1 and np.any(np.diff(t_frames) <= 0):
        raise DatasetError(f"{fcsv}: t_s must increase strictly")
    fps = float(meta.get("fps") or (1.0 / np.median(np.diff(t_frames)) if len(t_frames) > 1 else 30.0))
    truth = None
    if (root / "truth.csv").is_file():
        rows = _read_csv(root / "truth.csv", ("t_s", "lat_deg", "lon_deg", "h_ellipsoid_m", "h_msl_m", "roll_deg",
                                              "pitch_deg", "yaw_deg"), ("vn_mps", "ve_mps", "vd_mps"))
        if len(rows) != len(paths):
            raise DatasetError(f"{root / 'truth.csv'}: {len(rows)} rows but {len(paths)} frames (one truth row per frame)")
        truth = [_truth_pose(r, i, origin, T) for i, r in enumerate(rows)]
    gnss = []
    if (root / "gnss.csv").is_file():
        for r in _read_csv(root / "gnss.csv", ("t_s", "fix_type", "lat_deg", "lon_deg", "alt_msl_m", "h_ellipsoid_m",
                                               "eph", "epv", "satellites"),
                           ("h_acc_m", "v_acc_m", "vn_mps", "ve_mps", "vd_mps", "cog_deg")):
            vel = None if r["vn_mps"] is None else (r["vn_mps"], r["ve_mps"], r["vd_mps"])
            gnss.append(GnssSample(r["t_s"], GpsFixType(int(r["fix_type"])), r["lat_deg"], r["lon_deg"], r["alt_msl_m"],
                                   r["h_ellipsoid_m"], r["eph"], r["epv"],
                                   r["h_acc_m"] if r["h_acc_m"] is not None else math.nan,
                                   r["v_acc_m"] if r["v_acc_m"] is not None else math.nan,
                                   int(r["satellites"]), vel, r["cog_deg"]))
    attitude = []
    if (root / "attitude.csv").is_file():
        attitude = [AttitudeSample(r["t_s"], r["roll_rad"], r["pitch_rad"], r["yaw_rad"], r["baro_alt_m"])
                    for r in _read_csv(root / "attitude.csv", ATTITUDE_COLUMNS[:-1], ATTITUDE_COLUMNS[-1:])]
    return Dataset(root, str(meta.get("name", root.name)), fps, camera, T, origin, rough, gis_files, t_frames, paths,
                   truth, gnss, attitude, meta, p_gnss)
