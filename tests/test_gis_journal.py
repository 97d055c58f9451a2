"""Registration journal (gis.align.journal) and its offline replay (gis.align.replay): the worker
writes what it registered, the files round-trip, and a replay decides as the flight did."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from gis.align.fine import FineTuner
from gis.align.georef import GeorefCorrection
from gis.align.journal import (
    Journal,
    RegistrationJob,
    read_journal,
    read_record,
    read_truth,
    write_meta,
    write_record,
    write_truth,
)
from gis.align.replay import format_rows, main, replay
from gis.config import AlignmentConfig
from gis.model import GisModel
from gis.synthetic import box_city_model
from gis.types import Alignment, AlignmentSource
from tests.test_gis_align import ORIGIN, T_ECEF_SLAM, _distorted_cloud, _prior_about, _slam


@pytest.fixture(scope="module")
def city() -> GisModel:
    return box_city_model(600.0, ORIGIN, seed=1, spacing_m=1.0)


def _assert_same_alignment(a: Alignment, b: Alignment) -> None:
    np.testing.assert_array_equal(a.T_ecef_slam.matrix(), b.T_ecef_slam.matrix())
    np.testing.assert_array_equal(a.information_6x6, b.information_6x6)
    fields = ("source", "t_s", "reset_counter", "sigma_m", "fitness", "rmse_m", "n_points", "map_id", "scale_sigma",
              "drift_free_radius_m")
    assert [getattr(a, f) for f in fields] == [getattr(b, f) for f in fields]
    assert (a.center_slam is None and b.center_slam is None) or np.array_equal(a.center_slam, b.center_slam)


def _enu_axes() -> np.ndarray:
    """ECEF → horizontal (east, north) axes at the test site, (3, 2)."""
    from gis.geodesy import R_ecef_enu

    return R_ecef_enu(ORIGIN.lat0_deg, ORIGIN.lon0_deg)[:, :2]


def test_a_record_reads_back_as_written(tmp_path):
    cam = np.array([10.0, -5.0, 80.0])
    prior = replace(_prior_about(cam, (1.0, 0.5, 0.2)), drift_free_radius_m=120.0)  # (a survey map's T_rough)
    result = Alignment(prior.T_ecef_slam, AlignmentSource.FINE, 12.5, 2, 3 * np.eye(6), 0.8, 0.31, 0.25, 640, 1, None, 0.004)
    job = RegistrationJob(12.5, np.random.default_rng(0).normal(size=(50, 3)), prior, _slam(cam), 512.25, 0.4,
                          GeorefCorrection(np.array([2.0, -1.0, 0.3]), 0.5, 4))
    rec = read_record(write_record(tmp_path, 7, job, result, "ok"))
    assert rec.reason == "ok" and rec.job.t_s == 12.5
    np.testing.assert_array_equal(rec.job.points_slam, job.points_slam)
    np.testing.assert_array_equal(rec.job.center_slam, job.center_slam)
    assert (rec.job.camera_h_ell_m, rec.job.camera_h_sigma_m) == (512.25, 0.4)
    np.testing.assert_array_equal(rec.job.correction.offset_enu_m, job.correction.offset_enu_m)
    assert (rec.job.correction.sigma_m, rec.job.correction.n) == (0.5, 4)
    _assert_same_alignment(rec.job.initial, prior)
    _assert_same_alignment(rec.alignment, result)

    refused = RegistrationJob(13.0, job.points_slam, prior, _slam(cam))  # no barometer, no correction, refused
    rec = read_record(write_record(tmp_path, 8, refused, None, "fitness 0.12 < min_fitness 0.2"))
    assert rec.alignment is None and rec.reason.startswith("fitness")
    assert rec.job.camera_h_ell_m is None and rec.job.camera_h_sigma_m is None and rec.job.correction is None
    assert not list(tmp_path.glob("*.tmp.npz"))


def test_unreadable_journals_are_refused_by_name(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a registration journal"):
        read_journal(tmp_path)
    bad = tmp_path / "reg_000001.000_00000.npz"
    np.savez(bad, t_s=np.array(1.0))  # a record without its fields
    with pytest.raises(ValueError, match="reg_000001.000_00000.npz: not a readable registration record"):
        read_record(bad)
    assert read_truth(tmp_path) is None


def test_the_worker_journals_its_registrations_and_a_replay_decides_as_the_flight(city, tmp_path):
    """Real registrations in the fine-tuning worker process, written by the journal as they are
    handed over; the replay of the files against the same model gives the same alignments, and with
    the truth beside them says how far each put the camera (prior 2.2 m off, fused < 0.6 of that)."""
    from companion.fusion.registration import FineTuneWorker

    adopted = []
    config = AlignmentConfig()
    worker = FineTuneWorker(FineTuner(city, config), lambda a, r, ms, icp: adopted.append((a, r)), lag_s=0.3)
    worker.journal = Journal(tmp_path)
    write_meta(tmp_path, None, 1.0, config.model_dump(mode="json"), (ORIGIN.lat0_deg, ORIGIN.lon0_deg, ORIGIN.h0_ellipsoid_m))
    cams, times = [], []
    try:
        for k, (c_ground, dt) in enumerate([(np.array([20.0, -10, 0]), (2.0, -1.0, 0.5)),
                                            (np.array([-60.0, 40, 0]), (1.0, 1.5, -0.3))]):
            p, cam = _distorted_cloud(city, c_ground, seed=11 + k)
            t = 10.0 + 5 * k
            assert worker.submit(_slam(p), _prior_about(cam, dt), _slam(cam), t)
            worker.release(t + 0.3)
            cams.append(cam)
            times.append(t)
    finally:
        worker.close()
    assert [r for _, r in adopted] == ["ok", "ok"]
    write_truth(tmp_path, np.array(times), np.array([T_ECEF_SLAM.apply(_slam(c)[None])[0] for c in cams]))

    records = read_journal(tmp_path)
    assert [r.job.t_s for r in records] == times
    for rec, (a, _) in zip(records, adopted):
        _assert_same_alignment(rec.alignment, a)
    rows = replay(records, city, config, read_truth(tmp_path), scan=True)
    assert all(r.as_in_flight and r.reason == "ok" for r in rows)
    assert rows[0].prior_err_h_m == pytest.approx(np.hypot(2.0, -1.0), abs=0.05)
    assert all(r.fused_err_h_m < 0.6 * r.prior_err_h_m and r.fused_err_h_m <= 3 * r.sigma_m for r in rows)
    assert all(r.scan.n_starts == 25 and 1 <= r.scan.n_optima <= 25 and np.isfinite(r.scan.best_err_h_m) for r in rows)
    # started at the truth, the ICP leaves it for where the cloud fits: these clouds are tilted 1°
    # about their centroid relative to the camera 80 m above (_distorted_cloud), 1.4 m at the camera
    assert all(0.7 < r.scan.from_truth_err_h_m < 1.8 for r in rows)
    assert "started at the truth it settles" in format_rows(rows)
    assert "2 of 2 accepted" in format_rows(rows)
    assert all(r.cpu_ms > 0 for r in rows)
    assert f"registration CPU (thread time) mean {np.mean([r.cpu_ms for r in rows]):.1f} ms" in format_rows(rows)

    # as a chain, the second registration starts from the first one's replayed result, not its recorded prior
    chained = replay(records, city, config, read_truth(tmp_path), chain=True)
    assert chained[0].as_in_flight and chained[0].prior_err_h_m == rows[0].prior_err_h_m
    first = adopted[0][0]
    cam2 = _slam(cams[1])[None]
    assert chained[1].prior_err_h_m == pytest.approx(
        np.linalg.norm((first.T_ecef_slam.apply(cam2) - T_ECEF_SLAM.apply(cam2))[0] @ _enu_axes()), abs=1e-4)
    assert chained[1].prior_err_h_m != pytest.approx(rows[1].prior_err_h_m, abs=0.05)

    # a changed setting is replayed as such: with a fitness gate no registration passes, both are refused
    strict = replay(records, city, config.model_copy(update=dict(min_fitness=0.99)))
    assert all(not r.as_in_flight and r.reason.startswith("fitness") for r in strict)


def test_replay_command_needs_the_model_file_and_valid_settings(tmp_path, capsys):
    write_meta(tmp_path, None, 1.0, AlignmentConfig().model_dump(mode="json"), (47.0, 8.0, 400.0))
    with pytest.raises(SystemExit, match="not KEY=VALUE"):
        main([str(tmp_path), "--set", "no_such_setting=1"])
    with pytest.raises(SystemExit, match="names no GIS model file"):
        main([str(tmp_path)])


def test_the_scan_finds_the_clouds_own_floor_from_the_truth(city):
    """``--scan``'s start at the truth: an undistorted cloud stays there (a few decimetres), the
    same cloud tilted 1° about its centroid leaves it by about the tilt × the camera's 80 m height,
    wherever the prior (3 m off here) started the ICP."""
    from gis.align.replay import _scan
    from gis.synthetic import slam_like_cloud

    c_ground = np.array([20.0, -10, 0])
    cam = c_ground + np.array([0.0, 0.0, 80.0])
    truth = T_ECEF_SLAM.apply(_slam(cam)[None])[0]
    tuner = FineTuner(city, AlignmentConfig())
    prior = _prior_about(cam, (3.0, 0.0, 0.0))
    clean = slam_like_cloud(city, c_ground, 70, 3000, noise_m=0.3, seed=5)
    tilted, _ = _distorted_cloud(city, c_ground, seed=5)
    floor_clean = _scan(tuner, _slam(clean), prior, _slam(cam), truth).from_truth_err_h_m
    floor_tilted = _scan(tuner, _slam(tilted), prior, _slam(cam), truth).from_truth_err_h_m
    assert floor_clean < 0.4
    assert 0.7 < floor_tilted < 1.8
    assert np.isnan(_scan(tuner, _slam(clean), prior, _slam(cam), None).from_truth_err_h_m)
