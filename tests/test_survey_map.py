"""Survey map: a GNSS-free start (TerraSLAM §4.3 — T_rough applies online because the online SLAM
starts in the survey's map).

Our SLAM maps a simulated survey flight; its keyframes are registered to a stand-in reconstruction
frame (the truth's camera centres under an unknown similarity, where align-offline has COLMAP's)
and the survey's T_rough is carried into the map's frame, stored in the GIS cache and loaded the
way the service loads it. A second flight over the same site, 10 m higher and with GNSS denied
from take-off, must relocalise into the survey map and send fixes within 3σ of the truth.
The COLMAP path end to end: ``pytest -m slow tests/test_gis_cli.py -k colmap``.
"""
from __future__ import annotations

import re
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gis.align.survey import SurveyRegistrationFailed, register_centres
from gis.sim3 import Sim3

FPS = 10.0
N_SURVEY = 400
N_FLIGHT = 150


def _track(n: int = 40, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1.5 * np.pi, n)
    p = np.stack([60 * np.cos(t), 40 * np.sin(t), 80 + 3 * np.sin(3 * t)], 1) + rng.normal(0, 0.05, (n, 3))
    return {f"{i:06d}.png": p[i] for i in range(n)}


def test_register_centres_recovers_the_similarity_and_trims_a_bad_frame() -> None:
    dst = _track()
    T = Sim3(0.05, Rotation.from_euler("zyx", [40, -10, 5], degrees=True).as_matrix(), np.array([1.0, 2.0, -3.0]))
    src = {k: T.apply(v[None])[0] for k, v in dst.items()}  # SLAM units: 1 = 20 m
    src["000007.png"] = src["000007.png"] + 2.0  # one frame the SLAM placed 40 m off (in metres of dst)
    src["not-in-dst.png"] = np.zeros(3)
    reg = register_centres(src, dst)
    assert reg.n_pairs == 39
    assert reg.T_dst_src.scale == pytest.approx(20.0, rel=1e-3)
    moved = np.array([reg.T_dst_src.apply(src[k][None])[0] for k in dst if k != "000007.png"])
    assert np.abs(moved - np.array([v for k, v in dst.items() if k != "000007.png"])).max() < 0.3


def test_register_centres_refuses_what_it_cannot_determine() -> None:
    dst = _track()
    with pytest.raises(SurveyRegistrationFailed, match="only 3 frames"):
        register_centres({k: dst[k] for k in list(dst)[:3]}, dst)
    line = {f"{i}": np.array([i * 5.0, 0.0, 80.0]) for i in range(20)}
    with pytest.raises(SurveyRegistrationFailed, match="straight line"):
        register_centres(line, line)
    rng = np.random.default_rng(1)
    noisy = {k: v + rng.normal(0, 8.0, 3) for k, v in dst.items()}  # two tracks that do not agree
    with pytest.raises(SurveyRegistrationFailed, match="disagree"):
        register_centres(noisy, dst)


def test_cache_keeps_a_sites_survey_map_checks_its_hash_and_forgets_it(tmp_path) -> None:
    from gis.cache import CacheCorrupt, GisCache
    from gis.geodesy import LocalFrame
    from gis.synthetic import box_city_model

    cache = GisCache(tmp_path / "c")
    site = cache.save_model(box_city_model(100.0, LocalFrame(47.0, 8.0, 400.0), spacing_m=4.0), "s")
    assert cache.survey_map(site) is None
    with pytest.raises(KeyError):
        cache.save_survey_map("nope", tmp_path / "x")
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    a.write_bytes(b"first survey" * 100)
    b.write_bytes(b"second survey" * 100)
    first = cache.save_survey_map(site, a)
    assert cache.survey_map(site) == first and first.read_bytes() == a.read_bytes()
    second = cache.save_survey_map(site, b)
    assert cache.survey_map(site) == second and not first.exists()  # the replaced one is freed
    second.write_bytes(b"flipped" + b.read_bytes()[7:])
    with pytest.raises(CacheCorrupt, match="survey map .* SHA-256"):
        cache.survey_map(site)
    size = second.stat().st_size
    assert cache.remove(site) >= size and not second.exists()


def build_survey(tmp: Path, model=None, n_frames: int = N_SURVEY):
    """Our SLAM's map of the first ``n_frames`` of the `nominal` flight (10 fps; 400: 40 s, a side
    and a turn), its T_rough from a stand-in reconstruction (the truth's camera centres in a frame
    of unknown scale, rotation and origin, where align-offline has COLMAP's), stored in a GIS cache
    as align-offline stores it with ``model`` (default: any model, for the site's row).
    Returns (cache, site, scenario, registration, alignment)."""
    from companion.config import AppConfig
    from companion.sim import make_scenario
    from companion.survey import map_survey, save_survey_map, survey_alignment
    from gis.align.fine import enu_sim3
    from gis.cache import GisCache
    from gis.sim3 import compose
    from gis.synthetic import box_city_model

    sc = make_scenario("nominal", seed=0, fps=FPS, n_frames=n_frames)
    names = [f"{i:06d}.png" for i in range(n_frames)]
    sm = map_survey(sc.camera, sc.steps(), names, AppConfig().slam)
    try:
        T_colmap_enu = Sim3(0.02, Rotation.from_euler("zyx", [-70, 8, 3], degrees=True).as_matrix(), np.array([3.0, -1, 2]))
        colmap = {n: T_colmap_enu.apply(sc.truth.T_enu_cam[i][None, :3, 3])[0] for i, n in enumerate(names) if i % 4 == 0}
        colmap.update({n: T_colmap_enu.apply(sc.truth.T_enu_cam[int(n[:6])][None, :3, 3])[0] for n in sm.keyframe_centres})
        reg = register_centres(sm.keyframe_centres, colmap)
        T_rough_colmap = compose(enu_sim3(sc.origin), T_colmap_enu.inverse())  # what rough_align finds on the cloud
        a = survey_alignment(sm, compose(T_rough_colmap, reg.T_dst_src), sigma_m=1.5)
        cache = GisCache(tmp / "cache")
        site = cache.save_model(model if model is not None else box_city_model(100.0, sc.origin, spacing_m=4.0), "site-S")
        saved = save_survey_map(sm, tmp / "survey.npz", a, site)
        cache.save_survey_map(site, saved.path)
    finally:
        sm.close()
    return cache, site, sc, reg, a


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    return build_survey(tmp_path_factory.mktemp("survey"))


def test_survey_map_is_registered_on_its_keyframes(survey) -> None:
    _, _, sc, reg, a = survey
    assert reg.n_pairs >= 15 and reg.rmse_rel < 0.01, reg
    assert a.source.value == "rough" and a.sigma_m == 1.5


def test_service_starts_in_the_survey_map_and_fixes_without_gnss(survey, tmp_path) -> None:
    """GNSS denied from take-off: fixes from the first relocalised frame, within 3σ of the truth."""
    from companion.app import build_localizer
    from companion.config import AppConfig, SupervisorConfig
    from companion.pipeline import PipelineInput, attitude_prior
    from companion.service import _restore_alignment, _survey_map
    from companion.sim import make_scenario, scenario_spec
    from companion.sim.gnss import GnssEvent, GnssSpec
    from slam.types import TrackingState

    cache, site, sc, _, _ = survey
    assert _survey_map(cache, sc.camera, "another-site") is None  # (no survey map stored for it)
    restored = _survey_map(cache, sc.camera, site)
    assert restored is not None and restored.survey and restored.alignment is not None
    spec = scenario_spec("nominal")
    spec = replace(spec, name="denied", flight=replace(spec.flight, altitude_m=90.0), gnss=GnssSpec(events=(GnssEvent("dropout", 0.0),)))
    flight = make_scenario(spec=spec, seed=0, fps=FPS, n_frames=N_FLIGHT)  # same site (seed), 10 m higher
    cfg = AppConfig(supervisor=SupervisorConfig(state_dir=tmp_path))
    loc = build_localizer(cfg, flight.camera, flight.T_body_cam, None, initial_map=restored.loaded)
    _restore_alignment(cfg, loc, restored)
    t0 = time.monotonic()  # the camera's clock, as the service's frames carry it
    recs, truth = [], []
    try:
        for st in flight.steps():
            assert not any(g.fix_type >= 2 for g in st.gnss)  # no GNSS at all
            frame = replace(st.frame, t_s=t0 + st.frame.t_s)
            prior = attitude_prior(replace(st.attitude[-1], t_s=t0 + st.attitude[-1].t_s)) if st.attitude else None
            recs.append(loc.process(PipelineInput(frame, None, False, prior)))
            truth.append(st.truth.p_body_ecef_m)
    finally:
        loc.close()
    fixed = [(r, p) for r, p in zip(recs, truth) if r.fix is not None]
    err = np.array([np.linalg.norm(r.fix.p_ecef_m - p) for r, p in fixed])
    acc = np.array([np.hypot(r.fix.h_acc_m, r.fix.v_acc_m) for r, _ in fixed])
    print(f"survey start: first pose {recs[0].pose.state.name}, fixes {len(fixed)}/{len(recs)}, 3D error mean "
          f"{err.mean():.2f} / max {err.max():.2f} m, claimed 1-σ (h, v) median {np.median(acc):.2f} m; "
          f"(frame, error, claimed) {[(i, round(float(e), 1), round(float(s), 1)) for i, (e, s) in enumerate(zip(err, acc))][::10]}")
    assert recs[0].pose.state is TrackingState.RELOCALIZED or recs[1].pose.state is TrackingState.RELOCALIZED
    assert recs[0].pose.map_id == restored.loaded.header.map_id
    assert len(fixed) >= 0.9 * len(recs)
    assert np.all(err <= 3 * acc), err
    # tracked in the survey map, its points held in BA: 0.27-0.73 m mean, max 0.6-1.2 m over 8 surveys (with
    # the survey points free in BA: 1.1-3.3 m mean, and 2 of 13 surveys drifted to 20-30 m; before map
    # reuse: 10-30 m off within 2 s)
    assert err[0] < 1.5 and err.mean() < 1.5 and err.max() < 3.0


def _fly(loc, flight, n: int, with_gnss: bool):
    """Feed ``n`` frames of ``flight`` to the Localizer on the camera's clock; GNSS (the newest
    sample, trusted when it is a 3D fix) when ``with_gnss``. Returns (records, truth ECEF)."""
    from companion.pipeline import PipelineInput, attitude_prior

    t0 = time.monotonic()
    recs, truth, gnss = [], [], None
    for k, st in enumerate(flight.steps()):
        if k == n:
            break
        gnss = replace(st.gnss[-1], t_s=t0 + st.gnss[-1].t_s) if with_gnss and st.gnss else gnss
        frame = replace(st.frame, t_s=t0 + st.frame.t_s)
        prior = attitude_prior(replace(st.attitude[-1], t_s=t0 + st.attitude[-1].t_s)) if st.attitude else None
        recs.append(loc.process(PipelineInput(frame, gnss, gnss is not None and gnss.fix_type >= 3, prior)))
        truth.append(st.truth.p_body_ecef_m)
    return recs, truth


@pytest.mark.parametrize("survey_elsewhere", [False, True])
def test_survey_map_is_given_up_when_trusted_gnss_puts_the_vehicle_beyond_its_reach(survey, tmp_path, survey_elsewhere) -> None:
    """Taking off with good GNSS: over the surveyed area SLAM relocalises in the survey map as
    without GNSS; where GNSS puts the vehicle 2 km from every survey keyframe (here: the survey's
    T_rough moved 2 km east, the same images), the survey map is given up on the first frame and a
    fresh map starts collecting GNSS pairs for its bootstrap, instead of no SLAM map for
    gis.survey_reloc_timeout_s."""
    from companion.app import build_localizer
    from companion.config import AppConfig, SupervisorConfig
    from companion.service import _restore_alignment, _survey_map
    from companion.sim import make_scenario, scenario_spec
    from companion.sim.gnss import GnssSpec
    from gis.sim3 import compose

    cache, site, sc, _, _ = survey
    restored = _survey_map(cache, sc.camera, site)
    survey_id = restored.loaded.header.map_id
    if survey_elsewhere:
        d_ecef = sc.origin.R_ecef_enu @ np.array([2000.0, 0.0, 0.0])
        a = restored.alignment
        restored = replace(restored, alignment=replace(a, T_ecef_slam=compose(Sim3(1.0, np.eye(3), d_ecef), a.T_ecef_slam)))
    spec = scenario_spec("nominal")
    spec = replace(spec, name="gnss-good", flight=replace(spec.flight, altitude_m=90.0), gnss=GnssSpec(base="dgps"))
    flight = make_scenario(spec=spec, seed=0, fps=FPS, n_frames=N_FLIGHT)
    cfg = AppConfig(supervisor=SupervisorConfig(state_dir=tmp_path))
    loc = build_localizer(cfg, flight.camera, flight.T_body_cam, None, initial_map=restored.loaded,
                          reloc_timeout_s=cfg.gis.survey_reloc_timeout_s)
    _restore_alignment(cfg, loc, restored)
    logged = []
    loc.on_event = lambda t_s, text: logged.append(text)
    try:
        recs, truth = _fly(loc, flight, 20 if not survey_elsewhere else N_FLIGHT, with_gnss=True)
    finally:
        loc.close()
    given_up = [e for e in logged if e.startswith("survey map given up")]
    if not survey_elsewhere:
        assert any(r.pose.state.has_pose for r in recs[:2]) and recs[1].pose.map_id == survey_id
        assert not given_up
        return
    assert len(given_up) == 1 and 1500 <= int(re.search(r"vehicle (\d+) m from", given_up[0]).group(1)) <= 2100
    assert all(r.pose.map_id != survey_id for r in recs)  # never relocalised in it
    # a fresh map, tracked and collecting GNSS pairs for its bootstrap (which needs 40 m of track:
    # this flight's first 26 s; the bootstrap itself is tested in test_gis_align)
    fresh = [r for r in recs if r.pose.state.has_pose]
    assert len(fresh) >= 50 and loc.bootstrap.map_key == (fresh[-1].pose.map_id, fresh[-1].pose.reset_counter)
    assert len(loc.bootstrap.p_slam) >= 10
