"""Replay end to end on a real dataset written by the simulator: outputs in real formats, and no
global fix is ever emitted before an alignment exists (nothing guessed)."""
import csv
import json

from companion.app import run_replay
from companion.config import load_config
from companion.dataset import write_dataset
from companion.sim import make_scenario


def test_replay_writes_outputs_and_sends_nothing_without_alignment(tmp_path):
    ds = tmp_path / "ds"
    write_dataset(make_scenario("nominal", seed=3, n_frames=30), ds, progress=False)
    out = tmp_path / "out"
    summary = run_replay(load_config(environ={}), ds, out)
    assert summary["frames"] == 30
    # 1 s of flight is far too short a GNSS baseline for the bootstrap: no alignment, so no fix.
    assert summary["fix_ratio_all"] == 0.0
    with open(out / "trajectory.csv") as f:
        rows = list(csv.reader(f))
    assert rows[0][:4] == ["t_s", "lat_deg", "lon_deg", "h_ellipsoid_m"] and len(rows) == 1
    geo = json.loads((out / "trajectory.geojson").read_text())
    assert geo["type"] == "FeatureCollection" and geo["features"][0]["geometry"]["coordinates"] == []
    report = json.loads((out / "report.json").read_text())
    assert report["tracking_events"], "the SLAM timeline is reported"
    assert report["frame_latency_ms"]["mean"] > 0
    # how fast it ran against the recording: the frames' span over the loop's wall time
    from companion.dataset import read_dataset
    t = read_dataset(ds).frame_t_s
    pace = report["pace"]
    assert pace["mode"] == "unpaced" and abs(pace["recorded_s"] - (t[-1] - t[0])) < 1e-9 and pace["wall_s"] > 0
    assert abs(pace["speed_x"] - pace["recorded_s"] / pace["wall_s"]) < 1e-9


def test_replay_gives_each_frame_the_newest_attitude_up_to_0_1_s_old(tmp_path, monkeypatch):
    """A camera faster than the autopilot's ATTITUDE stream (a recorded flight: 30 fps against
    12.5 Hz) leaves frames with no attitude sample of their own; as in the service, they get the
    newest one while it is at most ATTITUDE_MAX_AGE_S old."""
    from companion.app import ATTITUDE_MAX_AGE_S
    from companion.pipeline import Localizer

    ds = tmp_path / "ds"
    write_dataset(make_scenario("nominal", seed=3, n_frames=30, fps=30), ds, progress=False)
    att = (ds / "attitude.csv").read_text().splitlines()
    (ds / "attitude.csv").write_text("\n".join([att[0]] + att[1::4]) + "\n")  # 50 Hz → 12.5 Hz
    kept = [float(line.split(",")[0]) for line in att[1::4]]
    seen = []
    process = Localizer.process
    monkeypatch.setattr(Localizer, "process", lambda self, inp: seen.append(inp) or process(self, inp))
    run_replay(load_config(environ={}), ds, tmp_path / "out")
    assert len(seen) == 30
    with_own_sample = 0
    for inp in seen:
        t = inp.frame.t_s
        newest = max((a for a in kept if a <= t), default=None)
        if newest is None or t - newest > ATTITUDE_MAX_AGE_S:
            assert inp.prior is None
        else:
            assert inp.prior is not None and inp.prior.t_s == newest
            with_own_sample += t - newest < 1 / 30
    assert 0 < with_own_sample < 25  # some frames had no sample since the previous one, and got a prior


def test_a_replay_with_gnss_denied_is_judged_against_the_withheld_gnss(tmp_path):
    """A flight without truth (what the recorder writes) replayed with GNSS denied from 13 s to
    17 s: the monitor sees 'no fix' from 13 s, the pipeline takes over, GNSS comes back at 17 s, and
    the fixes sent meanwhile are judged against the receiver's withheld solutions. Checked against
    an independent interpolation of gnss.csv in geodetic coordinates."""
    import numpy as np

    from companion.app import GnssDenial
    from gis.geodesy import LocalFrame

    ds = tmp_path / "ds"
    write_dataset(make_scenario("nominal", seed=0, n_frames=200, fps=10), ds, progress=False)
    (ds / "truth.csv").unlink()  # a recorded flight has none
    summary = run_replay(load_config(environ={}), ds, tmp_path / "out", deny=GnssDenial(13.0, 17.0))

    t_frames = [float(r["t_s"]) for r in csv.DictReader(open(ds / "images" / "frames.csv"))]
    t0 = t_frames[0]
    denied = [t for t in t_frames if t0 + 13.0 <= t < t0 + 17.0]
    assert summary["takeover_t_s"] == denied[0]
    events = [text for _, text in summary["switch_events"]]
    assert events[0] == "GNSS lost: no 3D fix (fix_type 1)" and events[-1] == "GNSS good again"
    assert summary["gnss_denial"]["frames"] == len(denied) == 40
    assert summary["after_takeover"]["n"] == 0 and summary["frames_with_truth"] == 0, "no truth: nothing is judged against it"

    fixes = list(csv.DictReader(open(tmp_path / "out" / "trajectory.csv")))
    during = [f for f in fixes if t0 + 13.0 <= float(f["t_s"]) < t0 + 17.0]
    assert summary["gnss_denial"]["fix_ratio"] == len(during) / len(denied) > 0.8
    gnss = [g for g in csv.DictReader(open(ds / "gnss.csv")) if int(g["fix_type"]) >= 3]
    tg = np.array([float(g["t_s"]) for g in gnss])
    frame = LocalFrame(float(gnss[0]["lat_deg"]), float(gnss[0]["lon_deg"]), 0.0)
    err_h, viol = [], 0
    for f in during:
        t = float(f["t_s"])
        ref = [np.interp(t, tg, [float(g[k]) for g in gnss]) for k in ("lat_deg", "lon_deg", "h_ellipsoid_m")]
        i = int(np.searchsorted(tg, t, side="right"))
        ref_h_acc = max(float(gnss[j]["h_acc_m"]) for j in ((i - 1,) if tg[i - 1] == t else (i - 1, i)))
        d = frame.geodetic_to_enu(float(f["lat_deg"]), float(f["lon_deg"]), float(f["h_ellipsoid_m"])) - frame.geodetic_to_enu(*ref)
        err_h.append(float(np.hypot(d[0], d[1])))
        viol += err_h[-1] > 3 * np.hypot(float(f["h_acc_m"]), ref_h_acc)
    ref = summary["against_withheld_gnss"]
    assert ref["n"] == len(during)
    assert abs(ref["horizontal_error_m"]["mean"] - np.mean(err_h)) < 0.01
    assert ref["integrity_violation_ratio"] == viol / len(during)
    assert ref["reference_h_acc_m"]["p50"] > 0
    assert (tmp_path / "out" / "error_over_time.png").stat().st_size > 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["gnss_denial"] == {"from_s": 13.0, "until_s": 17.0, "frames": 40, "fix_ratio": summary["gnss_denial"]["fix_ratio"]}


def test_replay_refuses_a_denial_it_cannot_run(tmp_path):
    import pytest
    from typer.testing import CliRunner

    from companion.app import GnssDenial
    from companion.cli import _register_subcommands, app

    with pytest.raises(ValueError, match="must come after its start"):
        GnssDenial(20.0, 10.0)
    with pytest.raises(ValueError, match="≥ 0 s"):
        GnssDenial(-1.0)
    _register_subcommands()
    runner = CliRunner()
    r = runner.invoke(app, ["replay", str(tmp_path), "--out", str(tmp_path / "o"), "--deny-gnss-until", "5"])
    assert r.exit_code == 2 and "needs --deny-gnss-from" in r.output
    r = runner.invoke(app, ["replay", str(tmp_path), "--out", str(tmp_path / "o"), "--deny-gnss-from", "5", "--deny-gnss-until", "5"])
    assert r.exit_code == 2 and "must come after its start" in r.output
    ds = tmp_path / "ds"
    write_dataset(make_scenario("nominal", seed=3, n_frames=20), ds, progress=False)
    r = runner.invoke(app, ["replay", str(ds), "--out", str(tmp_path / "o"), "--deny-gnss-from", "60"])
    assert r.exit_code == 2 and "frames end" in r.output


def test_the_gnss_reference_interpolates_only_between_close_3d_solutions():
    from dataclasses import replace

    import numpy as np
    import pytest

    from companion.evaluate import REFERENCE_MAX_GAP_S, GnssReference
    from mavlink_bridge.types import GnssSample, GpsFixType, no_fix_sample

    def sol(t, lat, h_acc=0.5):
        return GnssSample(t, GpsFixType.DGPS, lat, 8.0, 400.0, 450.0, 0.8, 1.1, h_acc, 0.8, 12)

    gap = REFERENCE_MAX_GAP_S + 0.5
    ref = GnssReference.from_samples([sol(0.0, 47.0), no_fix_sample(0.1), sol(0.2, 47.00001, 0.7),
                                      sol(0.2 + gap, 47.00002)])
    assert len(ref.t_s) == 3, "a no-fix report is no reference"
    p, acc = ref.at(0.1)
    a, b = ref.at(0.0)[0], ref.at(0.2)[0]
    assert np.allclose(p, (a + b) / 2, atol=1e-6) and acc == 0.7 and np.linalg.norm(b - a) > 1.0
    assert ref.at(0.2)[1] == 0.7
    assert ref.at(-0.1) is None and ref.at(0.2 + gap + 0.1) is None
    assert ref.at(0.3) is None, "across a gap longer than REFERENCE_MAX_GAP_S"
    # GPS_RAW_INT without alt_ellipsoid and h_acc: MSL + EGM96, HDOP × UERE (as the GNSS monitor reads it)
    bare = GnssReference.from_samples([replace(sol(0.0, 47.0), h_ellipsoid_m=float("nan"), h_acc_m=float("nan"))])
    assert np.all(np.isfinite(bare.p_ecef_m)) and bare.h_acc_m[0] == pytest.approx(0.8 * 2.0)


def test_a_reference_antenna_is_carried_to_the_body_origin_along_the_fix_attitude():
    """Heading east (yaw 90°), an antenna 0.2 m forward and 0.3 m above the body origin sits
    0.2 m east and 0.3 m up of it; without an attitude or a lever arm nothing moves."""
    from dataclasses import replace

    import numpy as np
    from scipy.spatial.transform import Rotation

    from companion.app import antenna_to_body
    from gis.geodesy import LocalFrame
    from gis.types import AlignmentSource, GlobalFix

    site = LocalFrame(47.3769, 8.5417, 450.0)
    body = site.enu_to_ecef(np.array([[10.0, 20.0, 60.0]]))[0]
    antenna = site.enu_to_ecef(np.array([[10.2, 20.0, 60.3]]))[0]
    x, y, z, w = Rotation.from_euler("ZYX", [90.0, 0.0, 0.0], degrees=True).as_quat()
    fix = GlobalFix(t_s=1.0, seq=1, p_ecef_m=body, lat_deg=47.3771, lon_deg=8.5418, h_ellipsoid_m=510.0, h_msl_m=462.0,
                    cov_ned_m2=np.eye(3) * 0.25, h_acc_m=0.5, v_acc_m=0.8, source=AlignmentSource.FINE,
                    q_ned_body=np.array([w, x, y, z]))
    lever = np.array([0.2, 0.0, -0.3])
    assert np.linalg.norm(antenna_to_body(antenna, fix, lever) - body) < 0.005
    assert antenna_to_body(antenna, replace(fix, q_ned_body=None), lever) is antenna
    assert antenna_to_body(antenna, fix, np.zeros(3)) is antenna


def test_replay_of_a_dataset_whose_gis_model_moved_takes_it_from_gis_model(tmp_path):
    """A recording names the GIS model where the companion computer had it: elsewhere the replay
    says so and takes the model given with --gis-model."""
    import shutil

    import yaml
    from typer.testing import CliRunner

    from companion.cli import _register_subcommands, app

    ds = tmp_path / "ds"
    write_dataset(make_scenario("nominal", seed=3, n_frames=12), ds, progress=False)
    (ds / "truth.csv").unlink()  # a recording has none
    site = yaml.safe_load((ds / "site.yaml").read_text())
    model = tmp_path / "elsewhere" / "model.ply"
    model.parent.mkdir()
    for suffix in ("", ".georef.json"):
        shutil.move(ds / (site["gis"]["files"][0] + suffix), str(model) + suffix)
    site["gis"]["files"] = ["/var/lib/terraslam/models/model.ply"]
    (ds / "site.yaml").write_text(yaml.safe_dump(site))
    _register_subcommands()
    runner = CliRunner()
    r = runner.invoke(app, ["replay", str(ds), "--out", str(tmp_path / "o1")])
    assert r.exit_code == 2 and "/var/lib/terraslam/models/model.ply does not exist" in r.output and "--gis-model" in r.output
    r = runner.invoke(app, ["replay", str(ds), "--out", str(tmp_path / "o2"), "--gis-model", str(tmp_path / "nowhere.ply")])
    assert r.exit_code == 2 and "nowhere.ply does not exist" in r.output
    r = runner.invoke(app, ["replay", str(ds), "--out", str(tmp_path / "o3"), "--gis-model", str(model)])
    assert r.exit_code == 0, r.output
    assert "none: the dataset has no truth.csv" in r.output and "3D error, all fixes" not in r.output
    assert json.loads((tmp_path / "o3" / "report.json").read_text())["frames"] == 12


def test_a_realtime_replay_feeds_frames_no_faster_than_they_were_recorded(tmp_path, monkeypatch):
    """--realtime: every frame reaches the pipeline no earlier than its recorded time after the
    first one (wall clock), and the report says how many came late; with --repeatable it is refused."""
    import time

    import pytest

    from companion.pipeline import Localizer

    ds = tmp_path / "ds"
    write_dataset(make_scenario("nominal", seed=3, n_frames=20, fps=10), ds, progress=False)
    seen = []
    process = Localizer.process
    monkeypatch.setattr(Localizer, "process", lambda self, inp: seen.append((time.perf_counter(), inp.frame.t_s)) or process(self, inp))
    summary = run_replay(load_config(environ={}), ds, tmp_path / "out", realtime=True)
    (w0, t0) = seen[0]
    assert len(seen) == 20
    # the pacer releases a step before its GNSS samples, the monitor and settle run, and that work
    # differs per frame (the first is slower), so a frame's process call is checked to within a
    # fifth of an interval of its recorded time; unpaced, frame 1 came 0.07 s early here
    for w, t in seen[1:]:
        assert w - w0 >= (t - t0) - 0.02, "a frame went to the pipeline before its recorded time"
    # paced: the loop takes at least the recorded span (the last frame waited for its time)
    assert summary["pace"]["mode"] == "realtime" and summary["pace"]["speed_x"] <= 1.0 + 0.02 / 1.9
    rt = summary["realtime"]
    assert rt["frames"] == 20 and abs(rt["frame_interval_ms"] - 100.0) < 1.0
    assert 0 <= rt["late_frames"] <= 20 and rt["late_ms_max"] >= rt["late_ms_mean"] >= 0.0
    assert json.loads((tmp_path / "out" / "report.json").read_text())["realtime"]["frames"] == 20
    with pytest.raises(ValueError, match="exclude each other"):
        run_replay(load_config(environ={}), ds, tmp_path / "out2", realtime=True, repeatable=True)
