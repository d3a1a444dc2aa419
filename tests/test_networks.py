"""Observation statistics against numpy."""

import jax.numpy as jnp
import numpy as np

from coherent_jax.networks import RunningStats, normalize, update_stats


def test_running_stats_equal_numpy_over_batches():
    rng = np.random.default_rng(0)
    chunks = [rng.normal(loc=3.0, scale=[0.5, 2.0, 7.0], size=(k, 3)) for k in (5, 17, 1, 40)]
    stats = RunningStats.create(3)
    for c in chunks:
        stats = update_stats(stats, jnp.asarray(c, jnp.float32))
    allx = np.concatenate(chunks)
    np.testing.assert_allclose(stats.mean, allx.mean(0), rtol=1e-5)
    np.testing.assert_allclose(stats.var, allx.var(0), rtol=1e-4)
    assert float(stats.count) == len(allx)


def test_normalize_standardizes_and_clips():
    stats = RunningStats(mean=jnp.array([1.0]), var=jnp.array([4.0]), count=jnp.array(10.0))
    np.testing.assert_allclose(normalize(stats, jnp.array([[3.0]])), [[1.0]], rtol=1e-6)
    np.testing.assert_allclose(normalize(stats, jnp.array([[1e6]])), [[10.0]])
    np.testing.assert_allclose(normalize(stats, jnp.array([[3.0]]), enabled=False), [[3.0]])
