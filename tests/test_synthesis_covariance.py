"""The refined window's covariance (service.inverse.synthesis.cluster_covariance, tile_clusters): the sandwich of a
least-squares fit whose errors are correlated within clusters, at the extremes (no residual, a singular
Jacobian, one cluster, clusters of one observation) and in what it is for: intervals that hold the truth where
the errors share a cluster's bias, which s^2 (J'J)^-1 does not see."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import t as student

from service.inverse.synthesis import TILE, cluster_covariance, tile_clusters

seeds = st.integers(0, 2**32 - 1)


def problem(seed: int, n: int = 60, k: int = 3, groups: int = 6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A random Jacobian (n, k), residuals (n,) and cluster labels (n,) using every one of ``groups``."""
    rng = np.random.default_rng(seed)
    clusters = np.concatenate([np.arange(groups), rng.integers(0, groups, n - groups)])
    return rng.normal(size=(n, k)), rng.normal(size=n), clusters


@given(seeds, st.floats(1e-6, 1e6))
@settings(max_examples=50, deadline=None)  # a shared machine's pauses are not the test's
def test_it_scales_with_the_residuals_squared_and_is_symmetric_positive_semidefinite(seed, scale):
    jacobian, residuals, clusters = problem(seed)
    found = cluster_covariance(jacobian, residuals, clusters)
    scaled = cluster_covariance(jacobian, scale * residuals, clusters)
    np.testing.assert_allclose(scaled, scale**2 * found, rtol=1e-9, atol=0)
    np.testing.assert_allclose(found, found.T, rtol=1e-12, atol=1e-15)
    assert np.linalg.eigvalsh(found).min() >= -1e-12 * np.abs(found).max()


@given(seeds, st.floats(1e-3, 1e3))
@settings(max_examples=50, deadline=None)  # a shared machine's pauses are not the test's
def test_a_parameter_in_other_units_gets_its_variance_in_those_units(seed, unit):
    """The search works in scaled units (parameters / _SCALE): the covariance follows the parameters' units."""
    jacobian, residuals, clusters = problem(seed)
    found = cluster_covariance(jacobian, residuals, clusters)
    rescaled = cluster_covariance(jacobian * np.array([unit, 1.0, 1.0]), residuals, clusters)
    np.testing.assert_allclose(rescaled[0, 0] * unit**2, found[0, 0], rtol=1e-8)
    np.testing.assert_allclose(rescaled[1:, 1:], found[1:, 1:], rtol=1e-8, atol=1e-14 * np.abs(found).max())


@given(seeds)
@settings(max_examples=50, deadline=None)  # a shared machine's pauses are not the test's
def test_no_residual_gives_no_spread(seed):
    jacobian, residuals, clusters = problem(seed)
    assert np.all(cluster_covariance(jacobian, 0.0 * residuals, clusters) == 0.0)


@given(seeds, st.integers(0, 2))
@settings(max_examples=50, deadline=None)  # a shared machine's pauses are not the test's
def test_a_direction_the_observations_do_not_pin_down_is_infinite_and_the_rest_as_without_it(seed, column):
    """A parameter that moves no residual (a mode died out before the window's first frame), or two that move them
    alike, get infinite variance; the others their covariance without them. A single cluster gives no spread."""
    jacobian, residuals, clusters = problem(seed)
    other = [j for j in range(3) if j != column]
    dead = jacobian.copy()
    dead[:, column] = 0.0
    found = cluster_covariance(dead, residuals, clusters)
    assert np.all(np.isposinf(found[column])) and np.all(np.isposinf(found[:, column]))
    np.testing.assert_allclose(
        found[np.ix_(other, other)], cluster_covariance(jacobian[:, other], residuals, clusters), rtol=1e-9
    )
    alike = jacobian.copy()
    alike[:, other[0]] = 2.5 * alike[:, column]
    found = cluster_covariance(alike, residuals, clusters)
    assert np.all(np.isposinf(found[[column, other[0]]])) and np.isfinite(found[other[1], other[1]])
    assert np.all(np.isposinf(cluster_covariance(jacobian, residuals, np.zeros_like(clusters))))
    assert np.all(np.isposinf(cluster_covariance(jacobian[:0], residuals[:0], clusters[:0])))


@given(seeds)
@settings(max_examples=50, deadline=None)  # a shared machine's pauses are not the test's
def test_clusters_of_one_observation_give_the_heteroskedasticity_robust_covariance(seed):
    jacobian, residuals, _ = problem(seed)
    n = len(residuals)
    bread = np.linalg.inv(jacobian.T @ jacobian)
    expected = bread @ (jacobian.T * residuals**2) @ jacobian @ bread * n / (n - 1)
    np.testing.assert_allclose(cluster_covariance(jacobian, residuals, np.arange(n)), expected, rtol=1e-9)


def test_its_intervals_hold_the_truth_where_each_cluster_shares_an_error_and_the_pixel_noise_s_do_not():
    """A line fitted to 20 clusters of 50 observations, each cluster's observations sharing an error 3 times their
    own noise (a highlight the renderer draws a little off): 95 % intervals at t(19) hold the true slope and
    intercept in 90-99 % of 400 such fits; those of s^2 (J'J)^-1 in well under two thirds of them."""
    rng = np.random.default_rng(7)
    groups, size = 20, 50
    clusters = np.repeat(np.arange(groups), size)
    truth = np.array([0.3, -1.2])
    held, naive = np.zeros(2), np.zeros(2)
    z, trials = student.ppf(0.975, groups - 1), 400
    for _ in range(trials):
        x = rng.normal(size=groups)[clusters] + 0.3 * rng.normal(size=clusters.size)  # a cluster's pixels alike
        jacobian = np.stack([x, np.ones_like(x)], axis=1)
        y = jacobian @ truth + 3.0 * rng.normal(size=groups)[clusters] + rng.normal(size=clusters.size)
        found = np.linalg.lstsq(jacobian, y, rcond=None)[0]
        residuals = jacobian @ found - y
        robust = np.sqrt(np.diag(cluster_covariance(jacobian, residuals, clusters)))
        plain = np.sqrt(np.diag(np.linalg.inv(jacobian.T @ jacobian)) * (residuals @ residuals) / (len(y) - 2))
        held += np.abs(found - truth) <= z * robust
        naive += np.abs(found - truth) <= 1.96 * plain
    assert np.all((0.90 <= held / trials) & (held / trials <= 0.99)), held / trials
    assert np.all(naive / trials < 0.67), naive / trials


@given(st.integers(1, 60), st.integers(1, 60), seeds)
@settings(max_examples=50, deadline=None)  # a shared machine's pauses are not the test's
def test_the_pixels_of_one_tile_share_a_cluster_and_the_clusters_are_the_tiles_in_use(height, width, seed):
    pixels = np.random.default_rng(seed).random(height * width) < 0.3
    labels = tile_clusters(pixels, (height, width))
    rows, columns = np.divmod(np.flatnonzero(pixels), width)
    tiles = list(zip(rows // TILE, columns // TILE))
    assert labels.shape == (pixels.sum(),)
    assert sorted(set(labels.tolist())) == list(range(len(set(tiles))))
    for i in range(len(tiles)):
        for j in range(i + 1, min(i + 40, len(tiles))):
            assert (labels[i] == labels[j]) == (tiles[i] == tiles[j])
