"""Accuracy of emitted fixes against ground truth, and the output files of a run.

evaluate(): per-fix 3D / horizontal / vertical error in the local NED frame at the truth
position, the integrity check (true horizontal error > 3 × reported 1-σ h_acc, TerraSLAM-style
accuracy figures mean/P50/P99/max). write_*(): the global trajectory as CSV (t, lat, lon, h),
TUM (t x y z qx qy qz qw, ENU metres at the site origin) and GeoJSON (RFC 7946 LineString).
"""
from __future__ import annotations

import csv
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from gis.geodesy import LocalFrame, R_ecef_enu, ecef_to_geodetic, geodetic_to_ecef
from gis.types import GlobalFix
from mavlink_bridge.monitor import h_acc_of, h_ellipsoid_of


def stats(x: np.ndarray) -> dict[str, float | None]:
    """mean / p50 / p99 / max of a 1-D array (None when empty)."""
    x = np.asarray(x, float)
    if x.size == 0:
        return {"mean": None, "p50": None, "p99": None, "max": None}
    return {"mean": float(x.mean()), "p50": float(np.percentile(x, 50)), "p99": float(np.percentile(x, 99)), "max": float(x.max())}


@dataclass(frozen=True)
class FixErrors:
    """Errors of the fixes that had a reference. t_s: (N,); err_ned_m: (N, 3); h_acc_m: (N,)
    reported. ref_h_acc_m: (N,) 1-σ horizontal accuracy of the reference itself (None: truth)."""

    t_s: np.ndarray
    err_ned_m: np.ndarray
    h_acc_m: np.ndarray
    ref_h_acc_m: np.ndarray | None = None

    @property
    def err_3d_m(self) -> np.ndarray:
        return np.linalg.norm(self.err_ned_m, axis=1)

    @property
    def err_h_m(self) -> np.ndarray:
        return np.linalg.norm(self.err_ned_m[:, :2], axis=1)

    @property
    def err_v_m(self) -> np.ndarray:
        return np.abs(self.err_ned_m[:, 2])

    def integrity_violation_ratio(self) -> float | None:
        """Fraction of fixes whose horizontal error exceeds 3 × their reported 1-σ h_acc; against
        a reference with its own error (a receiver), 3 × the two 1-σ added in quadrature (the
        difference of two independent errors)."""
        if len(self.t_s) == 0:
            return None
        sigma = self.h_acc_m if self.ref_h_acc_m is None else np.hypot(self.h_acc_m, self.ref_h_acc_m)
        return float(np.mean(self.err_h_m > 3.0 * sigma))

    def summary(self) -> dict:
        out = {
            "n": int(len(self.t_s)),
            "global_error_m": stats(self.err_3d_m),
            "horizontal_error_m": stats(self.err_h_m),
            "vertical_error_m": stats(self.err_v_m),
            "integrity_violation_ratio": self.integrity_violation_ratio(),
        }
        if self.ref_h_acc_m is not None:
            out["reference_h_acc_m"] = stats(self.ref_h_acc_m)
        return out


def gnss_ecef(sample) -> np.ndarray:
    """ECEF metres of a GnssSample (its ellipsoidal height as mavlink_bridge.monitor.h_ellipsoid_of)."""
    return geodetic_to_ecef(sample.lat_deg, sample.lon_deg, h_ellipsoid_of(sample))


#: A withheld GNSS track stands for the vehicle's position at a fix only between two of its 3D
#: solutions at most this far apart (1 Hz receivers included): over 1 s at 15 m/s, a turn of
#: 30 °/s bends the path ~0.2 m off the chord, within a DGPS solution's own error.
REFERENCE_MAX_GAP_S = 1.0


@dataclass(frozen=True)
class GnssReference:
    """The receiver's 3D solutions that a replay withheld from the pipeline (simulated denial): what
    a flight without truth.csv is judged against. Only as good as the receiver (its h_acc_m, RTK:
    centimetres, DGPS/SBAS: about a metre), and it is the antenna's position (run_replay carries it
    to the body origin with mount.yaml's p_body_gnss_m and each fix's attitude).
    t_s: (N,) increasing; p_ecef_m: (N, 3); h_acc_m: (N,) 1-σ."""

    t_s: np.ndarray
    p_ecef_m: np.ndarray
    h_acc_m: np.ndarray

    @classmethod
    def from_samples(cls, samples) -> "GnssReference":
        """From GnssSamples; solutions without a 3D fix are left out. Height and accuracy as the
        GNSS monitor reads them (MSL + EGM96 without alt_ellipsoid; HDOP × UERE without h_acc)."""
        good = [s for s in samples if s.fix_type >= 3]
        if not good:
            return cls(np.zeros(0), np.zeros((0, 3)), np.zeros(0))
        return cls(np.array([s.t_s for s in good], float), np.stack([gnss_ecef(s) for s in good]),
                   np.array([h_acc_of(s) for s in good], float))

    def at(self, t_s: float) -> tuple[np.ndarray, float] | None:
        """(ECEF position, 1-σ h_acc) at t_s, linear between the two solutions around it (the
        larger of their h_acc); None outside the track or across a gap over REFERENCE_MAX_GAP_S."""
        i = int(np.searchsorted(self.t_s, t_s, side="right"))  # the first solution after t_s
        if i == 0:
            return None
        if self.t_s[i - 1] == t_s:
            return self.p_ecef_m[i - 1].copy(), float(self.h_acc_m[i - 1])
        if i == len(self.t_s):
            return None
        t0, t1 = self.t_s[i - 1], self.t_s[i]
        if t1 - t0 > REFERENCE_MAX_GAP_S:
            return None
        w = (t_s - t0) / (t1 - t0)
        return (1 - w) * self.p_ecef_m[i - 1] + w * self.p_ecef_m[i], float(max(self.h_acc_m[i - 1], self.h_acc_m[i]))


def fix_errors(fixes: list[GlobalFix], truth_ecef_m: np.ndarray, ref_h_acc_m: np.ndarray | None = None) -> FixErrors:
    """Errors of ``fixes`` against reference positions (N, 3) ECEF given in the same order: the
    truth, or a receiver's positions with their 1-σ ``ref_h_acc_m`` (N,)."""
    ref = None if ref_h_acc_m is None else np.asarray(ref_h_acc_m, float).reshape(-1)
    if not fixes:
        return FixErrors(np.zeros(0), np.zeros((0, 3)), np.zeros(0), None if ref is None else np.zeros(0))
    p = np.stack([f.p_ecef_m for f in fixes])
    truth = np.asarray(truth_ecef_m, float).reshape(-1, 3)
    lat, lon, _ = ecef_to_geodetic(truth)
    err_ned = np.empty_like(p)
    for i in range(len(p)):  # rotation differs per point; N is at most tens of thousands
        R = R_ecef_enu(float(lat[i]), float(lon[i]))
        e_enu = (p[i] - truth[i]) @ R
        err_ned[i] = (e_enu[1], e_enu[0], -e_enu[2])
    return FixErrors(np.array([f.t_s for f in fixes]), err_ned, np.array([f.h_acc_m for f in fixes]), ref)


def velocity_errors(fixes: list[GlobalFix], truth_t_s: np.ndarray, truth_ecef_m: np.ndarray, max_dt_s: float = 0.25) -> dict:
    """How far each fix's NED velocity is from the truth's, and whether its speed accuracy covers
    it. The truth's velocity at a fix is the central difference of the truth positions
    (``truth_t_s`` ascending, (N, 3) ECEF) either side of the one at the fix's time, at most
    ``max_dt_s`` from it; fixes without a velocity, or without truth there, are left out. beyond_3sigma_ratio: fixes
    with a horizontal component beyond 3 × speed_acc_mps (the EKFs fuse each axis with it)."""
    t = np.asarray(truth_t_s, float)
    truth = np.asarray(truth_ecef_m, float).reshape(-1, 3)
    err, z = [], []
    for f in fixes:
        if f.v_ned_mps is None or f.speed_acc_mps is None:
            continue
        i = int(np.searchsorted(t, f.t_s))
        if not 1 <= i < len(t) - 1 or abs(t[i] - f.t_s) > 1e-6 or t[i + 1] - t[i - 1] > 2 * max_dt_s:
            continue
        lat, lon, _ = ecef_to_geodetic(truth[i])
        e_enu = (truth[i + 1] - truth[i - 1]) / (t[i + 1] - t[i - 1]) @ R_ecef_enu(float(lat), float(lon))
        e = np.asarray(f.v_ned_mps, float)[:2] - (e_enu[1], e_enu[0])
        err.append(float(np.hypot(*e)))
        z.append(float(np.max(np.abs(e))) / f.speed_acc_mps)
    z_arr = np.array(z)
    return {"n": len(err), "horizontal_error_mps": stats(np.array(err)),
            "beyond_3sigma_ratio": float(np.mean(z_arr > 3.0)) if z else None}


FIX_COLUMNS = ("t_s", "lat_deg", "lon_deg", "h_ellipsoid_m", "h_msl_m", "h_acc_m", "v_acc_m", "source")


def fix_row(x: GlobalFix) -> list[str]:
    """One trajectory.csv / fixes.csv row (FIX_COLUMNS)."""
    return [f"{x.t_s:.6f}", f"{x.lat_deg:.9f}", f"{x.lon_deg:.9f}", f"{x.h_ellipsoid_m:.4f}", f"{x.h_msl_m:.4f}",
            f"{x.h_acc_m:.4f}", f"{x.v_acc_m:.4f}", x.source.value]


def write_csv(fixes: list[GlobalFix], path: Path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(FIX_COLUMNS)
        w.writerows(fix_row(x) for x in fixes)


def write_tum(fixes: list[GlobalFix], origin: LocalFrame, path: Path) -> None:
    """TUM trajectory format: t x y z qx qy qz qw, position in ENU metres at ``origin``.

    Orientation is the body's in ENU when the fix carries q_ned_body, else identity.
    """
    R_enu_ned = np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])
    with open(path, "w") as f:
        f.write(f"# TUM trajectory, ENU metres at lat0={origin.lat0_deg} lon0={origin.lon0_deg} h0={origin.h0_ellipsoid_m} (WGS-84 ellipsoid)\n")
        for x in fixes:
            p = origin.ecef_to_enu(x.p_ecef_m)
            if x.q_ned_body is not None:
                qx, qy, qz, w = Rotation.from_matrix(R_enu_ned @ x.R_ned_body).as_quat()
            else:
                qx, qy, qz, w = 0.0, 0.0, 0.0, 1.0
            f.write(f"{x.t_s:.6f} {p[0]:.4f} {p[1]:.4f} {p[2]:.4f} {qx:.6f} {qy:.6f} {qz:.6f} {w:.6f}\n")


def write_geojson(fixes: list[GlobalFix], path: Path, properties: dict | None = None) -> None:
    """RFC 7946 FeatureCollection: one LineString of [lon, lat, h_ellipsoid] (WGS-84)."""
    coords = [[round(x.lon_deg, 9), round(x.lat_deg, 9), round(x.h_ellipsoid_m, 3)] for x in fixes]
    fc = {
        "type": "FeatureCollection",
        "features": [{
            "type": "Feature",
            "geometry": {"type": "LineString", "coordinates": coords},
            "properties": {"name": "terraslam", "height": "WGS-84 ellipsoidal metres", **(properties or {})},
        }],
    }
    path.write_text(json.dumps(fc))


def write_report(summary: dict, path_json: Path, path_md: Path | None = None, title: str = "TerraSLAM run") -> None:
    path_json.write_text(json.dumps(summary, indent=2, default=_json_default))
    if path_md is None:
        return
    lines = [f"# {title}", ""]
    for key, value in summary.items():
        if isinstance(value, dict):
            lines.append(f"- **{key}**: " + ", ".join(f"{k} {_fmt(v)}" for k, v in value.items()))
        elif isinstance(value, list):
            continue
        else:
            lines.append(f"- **{key}**: {_fmt(value)}")
    path_md.write_text("\n".join(lines) + "\n")


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.3f}"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_fmt(x)}" for k, x in v.items()) + "}"
    return str(v)


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if hasattr(o, "__dataclass_fields__"):
        return asdict(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
