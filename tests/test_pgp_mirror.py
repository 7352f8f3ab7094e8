"""pgp's mirror check (`jaxcal.mesh.pgp.mirror`, issue #24): a part of the layout locked in its mirror image is
found and moved back, as a brute force over every reflection finds it; a part hinged on two nodes alone has two
images and is left unplaced with one warning line; a layout without a mirror is left alone."""

import itertools
import logging

import numpy as np
import pytest

from jaxcal.mesh.pair_covariance import polish
from jaxcal.mesh.pgp import mirror

# a core of five nodes ranging each other (a0 = 0, a1 = 1, a2 = 2; hinge nodes 3 and 4) and a part of three
# (5, 6, 7) on one side of the line 3-4, ranging each other and both hinge nodes; `CROSS` ranges n7 to n1
# across the hinge, which decides the part's side
BASE = np.array([[0, 0], [20, 0], [3, 8], [8, 10], [15, 9], [9, 16], [14, 17], [18, 14]], dtype=float)
PART = np.array([5, 6, 7])
CROSS = (7, 1)
ANCHORS = (0, 1, 2)


def _edges(cross: bool) -> list[tuple[int, int]]:
    e = list(itertools.combinations(range(5), 2)) + list(itertools.combinations(PART.tolist(), 2))
    e += [(int(k), h) for k in PART for h in (3, 4)]
    return e + ([CROSS] if cross else [])


def _scene(rng, cross: bool, noise_m: float = 0.05):
    """(truth in the frame, (N, N) pair medians with NaN for unmeasured pairs, pair lists i, j, z)."""
    from jaxcal.mesh.frame import to_frame

    truth = to_frame(BASE + rng.uniform(-0.5, 0.5, BASE.shape), *ANCHORS)
    n = truth.shape[0]
    z = np.full((n, n), np.nan)
    for a, b in _edges(cross):
        z[a, b] = z[b, a] = np.linalg.norm(truth[a] - truth[b]) + rng.normal(0.0, noise_m)
    i, j = np.nonzero(np.triu(np.isfinite(z), 1))
    return truth, z, (i, j, z[i, j])


def _mirrored(truth, rng, jitter_m: float = 0.2):
    """The part reflected through the hinge line 3-4, every node moved by a filter-like error."""
    part = np.zeros(len(truth), bool)
    part[PART] = True
    x = mirror.reflect(truth, part, 3, 4) + rng.normal(0.0, jitter_m, truth.shape)
    x[0] = 0.0
    x[1, 1] = 0.0
    return x


def _brute_force(x, pairs, scale):
    """The polished layout of the lowest-cost reflection of any node subset (a0, a1 kept) through any
    measured pair's line: every one enumerated, the best polished."""
    i, j, z = pairs
    n = len(x)
    layouts = [x]
    for p, q in zip(i, j, strict=True):
        movable = [k for k in range(2, n) if k not in (p, q)]
        for r in range(1, len(movable) + 1):
            for sub in itertools.combinations(movable, r):
                part = np.zeros(n, bool)
                part[list(sub)] = True
                layouts.append(mirror.reflect(x, part, int(p), int(q)))
    costs = mirror.robust_cost(np.stack(layouts), i, j, z, scale)
    best = layouts[int(np.argmin(costs))]
    free = mirror._free(np.ones(n, bool), ANCHORS)
    out = polish(best, i, j, z, free, scale)
    return out * np.array([1.0, -1.0]) if out[2, 1] < 0 else out


def test_a_mirror_locked_part_is_moved_to_the_brute_force_image(rng):
    truth, z, pairs = _scene(rng, cross=True)
    x = _mirrored(truth, rng)
    ref = _brute_force(x, pairs, 0.3)
    out = mirror.check_mirrors(x, z, ANCHORS, 0.3)
    assert np.flatnonzero(out.moved).tolist() == PART.tolist()
    assert not out.ambiguous.any()
    assert out.gain[0] > mirror.MARGIN
    # the kept image is the brute force's, to the polish's tolerance; moved nodes carry the filter's offset
    np.testing.assert_allclose(out.fit, ref, atol=1e-3)
    assert np.linalg.norm(out.fit - truth, axis=1).max() < 0.2  # 5 cm ranges
    i, j, zz = pairs
    own = polish(x, i, j, zz, mirror._free(np.ones(len(x), bool), ANCHORS), 0.3)
    np.testing.assert_allclose(out.position[PART], (out.fit + x - own)[PART], atol=1e-9)
    assert np.linalg.norm(out.position[PART] - truth[PART], axis=1).max() < 1.5  # 0.2 m jitter, 3 sd * 2 axes
    np.testing.assert_array_equal(out.position[:5], x[:5])  # the rest keep the filter's cells


def test_a_layout_without_a_mirror_is_left_alone(rng):
    truth, z, _ = _scene(rng, cross=True)
    x = truth + rng.normal(0.0, 0.2, truth.shape)
    x[0], x[1, 1] = 0.0, 0.0
    out = mirror.check_mirrors(x, z, ANCHORS, 0.3)
    assert out.moves == () and not out.moved.any() and not out.ambiguous.any()
    np.testing.assert_array_equal(out.position, x)


@pytest.mark.parametrize("locked", [False, True])
def test_a_part_hinged_on_two_nodes_gets_a_covariance_over_both_images(rng, caplog, locked):
    from scipy.stats import chi2

    truth, z, _ = _scene(rng, cross=False)
    x = _mirrored(truth, rng) if locked else truth + rng.normal(0.0, 0.2, truth.shape)
    x[0], x[1, 1] = 0.0, 0.0
    out = mirror.check_mirrors(x, z, ANCHORS, 0.3)
    assert out.ambiguous[PART].all() and not out.ambiguous[:5].any()
    ranges = np.repeat(z[None], 3, axis=0)
    ids = tuple(f"n{k}" for k in range(len(x)))
    cov = np.repeat(np.eye(2)[None] * 0.3**2, len(x), axis=0)  # a pair-level width (0.3 m a coordinate)
    with caplog.at_level(logging.INFO, logger="jaxcal"):
        pos, c = mirror.resolve_mirrors(ranges, ids, ANCHORS, x, cov, 0.3)
        wide = mirror.span_undecided(ranges, ids, ANCHORS, pos, c, 0.3)
    np.testing.assert_array_equal(pos, x)  # no image is preferred: nothing moves
    np.testing.assert_array_equal(wide[:5], cov[:5])
    # both images inside the 95 % ellipse: the node's own place and the true part reflected through the hinge
    part = np.zeros(len(x), bool)
    part[PART] = True
    other = mirror.reflect(truth, part, 3, 4)
    if locked:
        other = truth
    for k in PART:
        e = other[k] - x[k]
        assert np.linalg.norm(e) > 2.0  # a distinct image
        assert e @ np.linalg.solve(wide[k], e) < chi2.ppf(0.95, 2)
        assert e @ np.linalg.solve(cov[k], e) > 40.0  # which the covariance alone would exclude
    warned = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warned) == 1 and "n5, n6, n7" in warned[0].getMessage()
