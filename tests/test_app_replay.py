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
