"""GNSS simulator statistics per mode, scripted timelines; autopilot attitude/baro signals."""
from __future__ import annotations

import math

import numpy as np
import pytest

from companion.sim import make_scenario
from companion.sim.gnss import MEAN_H_ERROR_M, GnssEvent, GnssSpec, parse_timeline, simulate_gnss
from gis.geodesy import LocalFrame
from mavlink_bridge.types import GpsFixType

ORIGIN = LocalFrame(47.3769, 8.5417, 455.0)


def _run(spec, duration_s=7200.0, h_agl=80.0, seed=0):
    t = np.arange(0, duration_s, 1 / spec.rate_hz)
    p = np.c_[np.zeros((len(t), 2)), np.full(len(t), 80.0)]
    p[:, 0] = 3.0 * t % 400  # moving east
    v = np.zeros_like(p)
    s = simulate_gnss(spec, ORIGIN, t, p, v, np.full(len(t), h_agl), seed=seed)
    ok = np.array([x.fix_type >= GpsFixType.FIX_2D for x in s])
    enu = np.full((len(s), 3), np.nan)
    if ok.any():
        enu[ok] = ORIGIN.geodetic_to_enu([x.lat_deg for x in np.array(s)[ok]], [x.lon_deg for x in np.array(s)[ok]],
                                         [x.h_ellipsoid_m for x in np.array(s)[ok]])
    return t, s, ok, enu - p


@pytest.mark.parametrize("mode, mean_m", [("standalone", 3.5), ("dgps", 0.7)])
def test_error_statistics_match_the_mode(mode, mean_m):
    t, s, ok, err = _run(GnssSpec(base=mode))
    assert ok.all()
    eh = np.hypot(err[:, 0], err[:, 1])
    assert MEAN_H_ERROR_M[mode] == pytest.approx(mean_m, rel=0.05)
    assert eh.mean() == pytest.approx(mean_m, rel=0.15)
    assert abs(err[:, 0].mean()) < 0.3 * mean_m  # unbiased over two hours
    # MSL vs ellipsoid differ by the EGM96 undulation (~48 m at Zurich)
    assert s[0].h_ellipsoid_m - s[0].alt_msl_m == pytest.approx(47.5, abs=2.0)
    assert {x.fix_type for x in s} == {GpsFixType.DGPS if mode == "dgps" else GpsFixType.FIX_3D}


def test_urban_degrades_with_decreasing_height():
    low = _run(GnssSpec(base="urban"), 1800, h_agl=15.0)
    high = _run(GnssSpec(base="urban"), 1800, h_agl=150.0)
    sats_low = np.mean([x.satellites for x in low[1]])
    sats_high = np.mean([x.satellites for x in high[1]])
    assert sats_low < sats_high - 3
    e_low = np.nanmean(np.hypot(low[3][:, 0], low[3][:, 1]))
    e_high = np.nanmean(np.hypot(high[3][:, 0], high[3][:, 1]))
    assert e_low > 1.5 * e_high
    assert np.mean([x.eph for x in low[1]]) > np.mean([x.eph for x in high[1]])


def test_scripted_dropout_jamming_and_spoofing():
    events = parse_timeline("dropout@10-20,jamming@40-70,spoof_drift@100-130,spoof_jump@150")
    assert [e.mode for e in events] == ["dropout", "jamming", "spoof_drift", "spoof_jump"] and events[-1].end_s is None
    spec = GnssSpec(rate_hz=10.0, events=events)
    t, s, ok, err = _run(spec, 170.0)
    fix = np.array([x.fix_type for x in s])
    sats = np.array([x.satellites for x in s])
    drop = (t >= 10) & (t < 20)
    assert (fix[drop] == GpsFixType.NO_FIX).all() and (fix[(t < 10)] == GpsFixType.FIX_3D).all()
    assert (fix[(t >= 20) & (t < 40)] == GpsFixType.FIX_3D).all()
    # jamming: satellites fall, the fix flaps before it is gone
    jam = (t >= 40) & (t < 70)
    assert sats[(t >= 40) & (t < 42)].mean() > sats[(t >= 60) & (t < 70)].mean() + 5
    early = fix[(t >= 42) & (t < 52)]
    assert (early == GpsFixType.NO_FIX).any() and (early == GpsFixType.FIX_3D).any()
    assert (fix[(t >= 56) & (t < 70)] == GpsFixType.NO_FIX).all()
    assert jam.any()
    # spoof drift: 0.5 m/s walk away with a perfect-looking fix
    sp = (t >= 100) & (t < 130)
    eh = np.hypot(err[sp, 0], err[sp, 1])
    assert eh[-1] == pytest.approx(0.5 * 30, abs=1.5)
    assert (fix[sp] == GpsFixType.FIX_3D).all() and (sats[sp] >= 12).all()
    assert max(x.h_acc_m for x in np.array(s)[sp]) < 2.0 and max(x.eph for x in np.array(s)[sp]) < 1.0
    # spoof jump: 40 m at once
    jm = t >= 150
    assert np.hypot(err[jm, 0], err[jm, 1]).min() > 38.0


def test_bad_timeline_and_modes_are_named():
    with pytest.raises(ValueError, match="bad GNSS timeline item 'dropout60'"):
        parse_timeline("dropout60")
    with pytest.raises(ValueError, match="mode must be one of"):
        GnssEvent("sunspots", 1.0)
    with pytest.raises(ValueError, match="end_s"):
        GnssEvent("dropout", 5.0, 2.0)
    with pytest.raises(ValueError, match="rate_hz"):
        GnssSpec(rate_hz=0.1)


def test_live_steps_carry_gnss_and_attitude_at_their_rates():
    sc = make_scenario("nominal", seed=2, n_frames=61)  # 2 s at 30 fps
    n_g = n_a = 0
    for st in sc.steps():
        n_g += len(st.gnss)
        n_a += len(st.attitude)
        for g in st.gnss:
            assert g.t_s <= st.frame.t_s
    assert n_g == len(sc.gnss_samples) == 11  # 5 Hz over [0, 2] s
    assert n_a == len(sc.attitude_samples) == 101  # 50 Hz
    # attitude ≈ truth (noise + bias of a few tenths of a degree), baro ≈ height above take-off
    from scipy.spatial.transform import Rotation

    from companion.sim.autopilot_signals import R_ned_body_at_vehicle

    tr = sc.truth
    ypr = Rotation.from_matrix(R_ned_body_at_vehicle(sc.origin, tr.T_enu_body[:, :3, :3], tr.lat, tr.lon)).as_euler("ZYX")
    att = sc.attitude_samples
    idx = [int(round(a.t_s * 30)) for a in att[::5]]
    d_roll = np.degrees([a.roll_rad for a in att[::5]] - ypr[idx, 2])
    d_yaw = np.degrees((np.array([a.yaw_rad for a in att[::5]]) - ypr[idx, 0] + math.pi) % (2 * math.pi) - math.pi)
    assert np.abs(d_roll).max() < 1.5 and np.abs(d_yaw).max() < 6.0
    h_agl0 = tr.T_enu_body[0, 2, 3] - sc.world.ground_height_m(*tr.T_enu_body[0, :2, 3])
    assert att[0].baro_alt_m == pytest.approx(h_agl0, abs=1.0)


def test_the_receiver_solves_for_its_antenna(tmp_path):
    """With ``gnss_antenna_m`` the simulated receiver reports its antenna: the same noise, displaced
    by the lever arm turned with the vehicle's attitude (R_enu_body · r), here 0.3 m behind and
    0.25 m above the body origin; datasets carry the offset in mount.yaml."""
    from companion.dataset import read_dataset, write_dataset

    r = (-0.3, 0.0, -0.25)
    plain, mast = make_scenario("nominal", seed=2, fps=10), make_scenario("nominal", seed=2, fps=10, gnss_antenna_m=r)  # the whole loop
    site = plain.origin
    t = np.array([g.t_s for g in plain.gnss_samples])
    a = np.array([site.geodetic_to_enu(g.lat_deg, g.lon_deg, g.h_ellipsoid_m) for g in plain.gnss_samples])
    b = np.array([site.geodetic_to_enu(g.lat_deg, g.lon_deg, g.h_ellipsoid_m) for g in mast.gnss_samples])
    _, _, _, R_enu_body = plain.trajectory.state(t)
    lever = np.einsum("nij,j->ni", R_enu_body, r)
    np.testing.assert_allclose(b - a, lever, atol=2e-3)
    assert np.ptp(lever[:, 0]) > 0.5 and np.ptp(lever[:, 1]) > 0.5 and np.all(lever[:, 2] > 0.15), \
        "the lever arm turns with the heading (a loop: east and north both swing ±0.3 m); the mast is up"
    ds = read_dataset(write_dataset(make_scenario("nominal", seed=2, n_frames=2, gnss_antenna_m=r), tmp_path / "ds", progress=False))
    assert ds.p_body_gnss_m.tolist() == list(r)
