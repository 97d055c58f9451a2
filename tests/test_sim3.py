import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gis.sim3 import Sim3, compose, umeyama


def random_sim3(rng, scale=None):
    return Sim3(scale if scale is not None else rng.uniform(0.2, 5.0), Rotation.random(random_state=rng.integers(1 << 31)).as_matrix(), rng.normal(0, 100, 3))


def test_compose_inverse_apply():
    rng = np.random.default_rng(1)
    A, B = random_sim3(rng), random_sim3(rng)
    p = rng.normal(size=(50, 3))
    np.testing.assert_allclose(compose(A, B).apply(p), A.apply(B.apply(p)), atol=1e-9)
    np.testing.assert_allclose(A.inverse().apply(A.apply(p)), p, atol=1e-9)
    np.testing.assert_allclose((A @ A.inverse()).matrix(), np.eye(4), atol=1e-9)
    np.testing.assert_allclose(Sim3.from_matrix(A.matrix()).matrix(), A.matrix(), atol=1e-9)


def test_apply_pose_keeps_rotation_unit_scale():
    rng = np.random.default_rng(2)
    S = random_sim3(rng, scale=3.0)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=3).as_matrix()
    T[:3, 3] = [1, 2, 3]
    out = S.apply_pose(T)
    np.testing.assert_allclose(out[:3, :3] @ out[:3, :3].T, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(out[:3, 3], S.apply(T[:3, 3]), atol=1e-9)


@pytest.mark.parametrize("offset", [0.0, 6.4e6])
def test_umeyama_recovers_similarity_with_scale(offset):
    rng = np.random.default_rng(4)
    truth = Sim3(2.7, Rotation.random(random_state=5).as_matrix(), np.array([offset, -offset / 3, 1234.0]))
    src = rng.uniform(-50, 50, size=(100, 3))
    dst = truth.apply(src) + rng.normal(0, 1e-3, size=(100, 3))
    est = umeyama(src, dst)
    assert abs(est.scale - truth.scale) < 1e-4
    np.testing.assert_allclose(est.R, truth.R, atol=1e-5)
    np.testing.assert_allclose(est.apply(src), dst, atol=5e-3)


def test_umeyama_rejects_bad_input():
    with pytest.raises(ValueError, match="at least 3"):
        umeyama(np.zeros((2, 3)), np.zeros((2, 3)))
    line = np.outer(np.arange(10.0), [1, 2, 3])
    with pytest.raises(ValueError, match="collinear"):
        umeyama(line, line)


def test_sim3_validation():
    with pytest.raises(ValueError, match="scale"):
        Sim3(0.0, np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="rotation"):
        Sim3(1.0, np.diag([1.0, 1.0, -1.0]), np.zeros(3))
