"""Simulator ↔ truth consistency through the public dataset reader (issue 3 "Done when")."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from companion.dataset import read_dataset, write_dataset
from companion.sim import make_scenario


def _project(ds, i, pts_enu):
    """Project ENU points with the truth pose and camera read back from disk (OpenCV model)."""
    T_cam_enu = np.linalg.inv(ds.truth[i].T_enu_cam)
    rvec, _ = cv2.Rodrigues(T_cam_enu[:3, :3])
    uv, _ = cv2.projectPoints(pts_enu.reshape(-1, 1, 3).astype(np.float64), rvec, T_cam_enu[:3, 3], ds.camera.K, ds.camera.dist)
    return uv.reshape(-1, 2)


@pytest.fixture(scope="module", params=["nominal", "distorted"])
def written(request, tmp_path_factory):
    sc = make_scenario(request.param, seed=3, n_frames=4)
    out = write_dataset(sc, tmp_path_factory.mktemp(request.param), progress=False)
    return sc, read_dataset(out)


def test_drawn_points_project_to_their_pixels_subpixel(written):
    """Every world point the renderer drew at a pixel centre projects back onto that pixel centre
    with the truth pose + calibration read from disk (also through lens distortion)."""
    sc, ds = written
    assert ds.n_frames == 4 and ds.camera.is_distorted == sc.camera.is_distorted
    for i in (0, 3):
        out = sc.render(i)
        v, u = np.mgrid[0:480:7, 0:640:9]
        p = out.points_enu[v, u]
        ok = np.all(np.isfinite(p), axis=-1)
        assert ok.mean() > 0.9  # the camera looks at the city, not at the sky
        uv = _project(ds, i, p[ok])
        err = np.linalg.norm(uv - np.stack([u[ok], v[ok]], 1), axis=1)
        assert np.percentile(err, 99) < 0.05, f"frame {i}: reprojection error P99 {np.percentile(err, 99):.3f} px"


def test_building_roofs_appear_where_truth_projects_them(written):
    """Known roof points (from the world description, not from the renderer) land on their building."""
    sc, ds = written
    out = sc.render(2)
    hits = checked = 0
    for b in sc.world.buildings:
        c = b.outline_enu.mean(0)
        pts = np.c_[0.8 * b.outline_enu + 0.2 * c, np.full(len(b.outline_enu), b.roof_z_m)]  # just inside the roof edge
        uv = _project(ds, 2, pts)
        cam = (np.linalg.inv(ds.truth[2].T_enu_cam) @ np.c_[pts, np.ones(len(pts))].T)[:3].T
        for (x, y), pc, pw in zip(uv, cam, pts):
            if pc[2] <= 0 or not (2 <= x < 638 and 2 <= y < 478):
                continue
            xi, yi = int(round(x)), int(round(y))
            if abs(out.depth_m[yi, xi] * 1.0 - np.linalg.norm(pw - ds.truth[2].T_enu_cam[:3, 3])) > 2.0:
                continue  # occluded by something nearer
            checked += 1
            hits += b.id in out.element[yi - 1:yi + 2, xi - 1:xi + 2]
    assert checked >= 5
    assert hits == checked


def test_images_on_disk_are_the_rendered_frames(written):
    sc, ds = written
    img = ds.image(1)
    ref = sc.render(1).image_bgr
    assert img.shape == (480, 640, 3) and img.dtype == np.uint8
    # same scene, independent sensor noise: small mean absolute difference, high correlation
    diff = np.abs(img.astype(float) - ref.astype(float)).mean()
    assert diff < 8.0
    assert np.corrcoef(img.ravel(), ref.ravel())[0, 1] > 0.95


def test_texture_everywhere_and_lighting_variants():
    orb = cv2.ORB_create(2000)
    means, saturated = {}, {}
    for name in ("nominal", "dark", "bright", "survey"):
        sc = make_scenario(name, seed=1, n_frames=31)
        img = sc.render(30).image_bgr
        g = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        kps = orb.detect(g, None)
        xy = np.array([k.pt for k in kps])
        # features spread over the image: every cell of a 4x4 grid has some
        cells = np.histogram2d(xy[:, 0], xy[:, 1], bins=4, range=[[0, 640], [0, 480]])[0]
        assert len(kps) > (200 if name == "dark" else 800), f"{name}: only {len(kps)} ORB features"
        assert (cells > 3).all() or name == "dark", f"{name}: textureless regions {cells}"
        means[name], saturated[name] = g.mean(), (g >= 250).mean()
    assert means["dark"] < 0.6 * means["nominal"] and means["bright"] > 1.5 * means["nominal"]
    assert saturated["bright"] > 0.1 > saturated["nominal"]


def test_motion_blur_in_fast_flight():
    from dataclasses import replace

    sc = make_scenario("fast", seed=1, n_frames=400)
    sharp = make_scenario("fast", seed=1, n_frames=400, spec=replace(sc.spec, motion_blur=False))
    assert np.hypot(*sc._motion_px(399)) > 1.0  # ~13 m/s at 80 m with a 1/30 s exposure
    lap = [cv2.Laplacian(cv2.cvtColor(s.render(399).image_bgr, cv2.COLOR_BGR2GRAY), cv2.CV_64F).var() for s in (sc, sharp)]
    assert lap[0] < 0.8 * lap[1]
