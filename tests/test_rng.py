"""hedger_jax.rng: the unrolled Threefry-2x32 equals JAX's, and the draws are well formed."""
import jax
import jax.extend.random as jr
import jax.numpy as jnp
import numpy as np
from scipy import stats

from hedger_jax import rng


def test_threefry_matches_jax():
    key = jax.random.PRNGKey(1234)
    x0 = jnp.arange(257, dtype=jnp.uint32) * jnp.uint32(2654435761)
    x1 = x0 ^ jnp.uint32(0xDEADBEEF)
    want = jr.threefry_2x32(key, jnp.concatenate([x0, x1]))
    y0, y1 = jax.jit(rng.threefry2x32)(rng.key_data(key), x0, x1)
    np.testing.assert_array_equal(np.concatenate([y0, y1]), np.asarray(want))


def test_typed_and_raw_keys_agree():
    np.testing.assert_array_equal(rng.uniform(jax.random.PRNGKey(3), 5),
                                  rng.uniform(jax.random.key(3), 5))


def test_uniform_range_and_distribution():
    u = np.asarray(rng.uniform(jax.random.PRNGKey(0), 200_001), np.float64)
    assert u.min() >= 0.0 and u.max() < 1.0
    assert stats.kstest(u, "uniform").pvalue > 1e-3
    n = np.asarray(rng.normal_from_uniform(jnp.asarray(u[:100_000], jnp.float32),
                                           jnp.asarray(u[100_000:200_000], jnp.float32)))
    assert np.isfinite(n).all() and stats.kstest(n, "norm").pvalue > 1e-3


def test_fold_in_gives_independent_keys():
    key = jax.random.PRNGKey(7)
    ks = jax.vmap(rng.fold_in, (None, 0))(key, jnp.arange(1000))
    assert ks.shape == (1000, 2) and ks.dtype == jnp.uint32
    assert len({tuple(k) for k in np.asarray(ks).tolist()}) == 1000
    a = np.asarray(jax.vmap(lambda k: rng.uniform(k, 1)[0])(ks), np.float64)
    assert stats.kstest(a, "uniform").pvalue > 1e-3
    # Different data, different key; the same data, the same key (pure).
    np.testing.assert_array_equal(rng.fold_in(key, 5), ks[5])
