"""``hedger_jax.canonical.canonical_order`` against a NumPy reference."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hedger_jax.canonical import canonical_order


def test_capacity_leaves_room_for_the_padding_keys():
    from hedger_jax import HedgerConfig
    HedgerConfig(2, 1, capacity=2**31 - 1 - 32, max_neighbours=32)
    with pytest.raises(ValueError, match="capacity"):
        HedgerConfig(2, 1, capacity=2**31 - 32, max_neighbours=32)


def _reference(idx, d2, mask):
    real = np.flatnonzero(mask)
    perm = np.concatenate([real[np.argsort(idx[real], kind="stable")], np.flatnonzero(~mask)])
    return idx[perm], d2[perm], np.arange(len(idx)) < mask.sum()


@pytest.mark.parametrize("w", [1, 5, 16, 32])
def test_canonical_order_matches_numpy(w):
    rng = np.random.default_rng(w)
    f = jax.jit(jax.vmap(canonical_order))
    idx = np.stack([rng.permutation(1000)[:w] for _ in range(64)]).astype(np.int32)
    idx[:8] = np.int32(2**31 - 1 - w) - 1 - np.arange(w)      # the largest slots allowed
    d2 = rng.uniform(0, 1, (64, w)).astype(np.float32)
    mask = rng.uniform(size=(64, w)) < rng.uniform(size=(64, 1))
    mask[0], mask[1] = True, False
    out = jax.device_get(f(jnp.asarray(idx), jnp.asarray(d2), jnp.asarray(mask)))
    for i in range(64):
        for got, want in zip(out, _reference(idx[i], d2[i], mask[i])):
            np.testing.assert_array_equal(got[i], want)


def test_ordering_a_prefix_then_padding_equals_ordering_the_whole():
    """The claim ``index.select`` relies on: entries after the first w' all padding, ordering
    the first w' and appending the padding gives the whole set's order."""
    rng = np.random.default_rng(1)
    idx = np.concatenate([rng.permutation(50)[:16], np.zeros(16, int)]).astype(np.int32)
    d2 = np.concatenate([rng.uniform(0, 1, 16), np.full(16, np.inf)]).astype(np.float32)
    mask = np.concatenate([rng.uniform(size=16) < 0.5, np.zeros(16, bool)])
    whole = canonical_order(jnp.asarray(idx), jnp.asarray(d2), jnp.asarray(mask))
    part = canonical_order(jnp.asarray(idx[:16]), jnp.asarray(d2[:16]), jnp.asarray(mask[:16]))
    for a, b, tail in zip(whole, part, (idx[16:], d2[16:], mask[16:])):
        np.testing.assert_array_equal(np.asarray(a), np.concatenate([np.asarray(b), tail]))
