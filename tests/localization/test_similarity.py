"""Correntropy similarity rate and trimmed-ICP overlap ratio (docking paper, sec. 3.2-3.4)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.stats import spearmanr

from dfusion.errors import ShapeError, ValidationError
from dfusion.localization import scan_to_points
from dfusion.geometry import se2_between
from dfusion.maps import cast_rays, OccupancyGrid
from dfusion.localization import correntropy_similarity, similarity_rate, SimilarityRate, trimmed_overlap_ratio
from dfusion.geometry import transform_points
from dfusion.maps.buildings import rooms

ANGLES = np.linspace(-math.pi, math.pi, 720, endpoint=False)   # 720 beams, 0.5 deg


@pytest.fixture(scope="module")
def scans():
    """The paper's Fig. 2 set-up: a data scan with uniform noise and Gaussian clutter; a model
    scan from a nearby pose in the map with an added obstacle, to be cropped."""
    g = rooms(16.0, 10.0, 3, 2, seed=2)
    data = g.data.copy()
    i, j = g.world_to_cell(np.array([[5.0, 2.0], [5.4, 2.4]]))
    data[i[0]:i[1] + 1, j[0]:j[1] + 1] = 100                    # a box the data scan does not see
    g2 = OccupancyGrid(data, g.resolution, g.origin)
    A = np.array([4.0, 3.0, 0.3])
    B = np.array([4.2, 3.1, 0.4])
    rng = np.random.default_rng(0)
    X = scan_to_points(cast_rays(g, A[None], ANGLES, 30.0)[0], ANGLES, 30.0)
    X = X + rng.uniform(-0.02, 0.02, X.shape)
    X = np.vstack([X, rng.normal(0.0, 2.0, (36, 2))])            # 5 % clutter
    Y = scan_to_points(cast_rays(g2, B[None], ANGLES, 30.0)[0], ANGLES, 30.0)
    return X, Y, se2_between(B, A)


def _homogeneous(p):
    c, s = math.cos(p[2]), math.sin(p[2])
    return np.array([[c, -s, p[0]], [s, c, p[1]], [0.0, 0.0, 1.0]])


def test_relative_pose_matches_se2_between():
    # the relative pose of b seen from a is a^-1 b, computed here with homogeneous matrices
    a, b = np.array([1.0, 2.0, 0.3]), np.array([-0.5, 0.7, -2.9])
    T = np.linalg.solve(_homogeneous(a), _homogeneous(b))
    expected = np.array([T[0, 2], T[1, 2], math.atan2(T[1, 0], T[0, 0])])
    np.testing.assert_allclose(se2_between(a, b), expected, atol=1e-12)
    p = np.array([[1.0, 0.0], [0.0, 2.0]])
    np.testing.assert_allclose(transform_points(p, (1.0, -1.0, math.pi / 2)), [[1.0, 0.0], [-1.0, -1.0]], atol=1e-12)


def test_rate_on_inlier_outlier_distances_is_the_inlier_fraction():
    rng = np.random.default_rng(1)
    overlaps = []
    for p in (0.3, 0.55, 0.7, 0.85):
        n_in = int(p * 1000)
        d = np.concatenate([np.abs(rng.normal(0, 0.02, n_in)), rng.uniform(0.5, 3.0, 1000 - n_in)])
        rate, sigma = correntropy_similarity(rng.permutation(d))
        assert rate == pytest.approx(p, abs=0.03), p
        assert sigma < 0.05 or p < 0.5
        overlaps.append(trimmed_overlap_ratio(d))
    # trimmed ICP's ratio (lambda = 2) rises too, but underestimates and stops at eta_min
    assert overlaps[0] == 0.4 and np.all(np.diff(overlaps) > 0) and overlaps[-1] < 0.85
    # only Gaussian residuals: the far tail of the noise is counted as unlike
    d = np.abs(rng.normal(0, 0.02, 1000))
    assert 0.8 < correntropy_similarity(d)[0] < 0.95


def test_std_kernel_width_underestimates_and_the_cap_guards_low_overlap():
    """Two documented choices: sigma about zero (rms), and the cap below 50 % overlap."""
    rng = np.random.default_rng(2)
    d = np.concatenate([rng.uniform(0, 0.05, 800), rng.uniform(0.5, 3.0, 200)])
    assert correntropy_similarity(d, sigma_mode="std")[0] < 0.5       # about 0.4 x 0.8
    assert correntropy_similarity(d)[0] == pytest.approx(0.8, abs=0.03)
    low = np.concatenate([rng.uniform(0, 0.05, 300), rng.uniform(0.6, 2.0, 700)])
    assert correntropy_similarity(low, max_sigma=math.inf)[0] > 0.55  # paper's rule: fooled
    assert correntropy_similarity(low)[0] == pytest.approx(0.3, abs=0.05)


def test_similarity_rises_with_the_true_overlap(scans):
    X, Yfull, T = scans
    crops = np.linspace(0.1, 1.0, 10)
    for dt, dth in [(0.0, 0.0), (0.1, math.radians(7)), (0.2, math.radians(14))]:
        gt, rate = [], []
        for c in crops:
            Y = Yfull[: int(c * len(Yfull))]                 # contiguous sector kept
            d, _ = cKDTree(Y).query(transform_points(X, T))
            gt.append(np.mean(d < 0.1))                      # true overlap at the true transform
            rate.append(SimilarityRate(Y)(X, T + np.array([dt, 0.0, dth])))
        gt, rate = np.array(gt), np.array(rate)
        assert np.all(np.diff(gt) > 0)
        assert spearmanr(gt, rate).statistic > 0.9, (dt, rate)
        assert np.all(np.diff(rate) > -0.05), rate           # monotone within tolerance
        if dt == 0.0:   # at the true transform: close to it above 50 %, higher below
            np.testing.assert_allclose(rate[gt >= 0.5], gt[gt >= 0.5], atol=0.05)
            assert np.all(rate >= gt - 0.05) and np.all(rate <= gt + 0.15)


def test_grid_lookup_agrees_with_the_kdtree(scans):
    X, Y, T = scans
    k = SimilarityRate(Y)
    g = SimilarityRate(Y, nearest="grid", grid_resolution=0.02)
    for P in (T, T + [0.05, 0.02, 0.03], T + [0.3, -0.2, 0.2]):
        dk, dg = k.distances(X, P), g.distances(X, P)
        assert np.all(dg >= dk - 1e-12)                      # never nearer than the nearest
        assert np.percentile(dg - dk, 95) <= 0.02 * math.sqrt(2) + 1e-9
        assert abs(k(X, P) - g(X, P)) < 0.05
    r = g.evaluate(X, T)
    assert r.n == len(X) and 0 < r.rate <= 1 and 0.4 <= r.overlap <= 1 and r.sigma <= 0.3


def test_one_off_functions_and_validation(scans):
    X, Y, T = scans
    assert similarity_rate(X, Y, T) == SimilarityRate(Y)(X, T)
    with pytest.raises(ShapeError):
        SimilarityRate(np.zeros((2, 2)))
    with pytest.raises(ValidationError):
        SimilarityRate(Y, nearest="brute")
    with pytest.raises(ValidationError):
        correntropy_similarity([0.1, 0.2])
