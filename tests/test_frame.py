import numpy as np
import pytest

from jaxcal.mesh.frame import align_rigid, apply_rigid, to_frame


def _random_rigid(rng, d, reflect=False):
    q, _ = np.linalg.qr(rng.normal(size=(d, d)))
    if (np.linalg.det(q) < 0) != reflect:
        q[:, 0] *= -1
    return q, rng.normal(size=d) * 10


@pytest.mark.parametrize("d", [2, 3])
def test_frame_conventions(rng, d):
    for _ in range(20):
        p = rng.uniform(-20, 20, (6, d))
        f = to_frame(p, 2, 4, 1)
        assert np.allclose(f[2], 0, atol=1e-12)
        assert f[4][0] > 0 and np.allclose(f[4][1:], 0, atol=1e-12)
        assert f[1][1] > 0
        if d == 3:
            assert abs(f[1][2]) < 1e-12
        # distances preserved
        dp = np.linalg.norm(p[:, None] - p[None], axis=-1)
        df = np.linalg.norm(f[:, None] - f[None], axis=-1)
        assert np.allclose(dp, df)


@pytest.mark.parametrize("d", [2, 3])
def test_frame_invariant_under_rigid_motion(rng, d):
    p = rng.uniform(-20, 20, (7, d))
    r, t = _random_rigid(rng, d)
    assert np.allclose(to_frame(p, 0, 1, 2), to_frame(apply_rigid(p, r, t), 0, 1, 2), atol=1e-9)
    # a mirror image gives the same frame coordinates in 2-D (a2 fixes the sign of y)
    if d == 2:
        m = p * np.array([1.0, -1.0])
        assert np.allclose(to_frame(p, 0, 1, 2), to_frame(m, 0, 1, 2), atol=1e-9)


def test_frame_nan_rows_and_degenerate():
    p = np.array([[0, 0], [1, 0], [0, 1], [np.nan, np.nan]], dtype=float)
    f = to_frame(p, 0, 1, 2)
    assert np.isnan(f[3]).all()
    with pytest.raises(ValueError, match="collinear"):
        to_frame(np.array([[0, 0], [1, 0], [2, 0]], dtype=float), 0, 1, 2)


@pytest.mark.parametrize("d, reflect", [(2, False), (2, True), (3, False), (3, True)])
def test_align_recovers_motion(rng, d, reflect):
    truth = rng.uniform(-20, 20, (8, d))
    r, t = _random_rigid(rng, d, reflect)
    est = apply_rigid(truth, r, t)
    est[3] = np.nan
    r2, t2 = align_rigid(est, truth, reflection=True)
    back = apply_rigid(est, r2, t2)
    ok = np.isfinite(est).all(axis=1)
    assert np.allclose(back[ok], truth[ok], atol=1e-9)
    if reflect:
        r3, t3 = align_rigid(est, truth, reflection=False)
        assert np.linalg.det(r3) > 0
        assert np.abs(apply_rigid(est, r3, t3)[ok] - truth[ok]).max() > 1e-3
