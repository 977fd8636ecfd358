"""Cheap per-step random draws for the acting loops: one fused kernel per draw.

``jax.random`` on the CPU lowers its threefry hash as a rolled 5-trip loop (to keep compile
times down), so every ``split``/``uniform``/``randint`` inside a jitted per-step loop costs a
small while loop of ~20 XLA operations; an epsilon-greedy step made about nine of them
(measured: ~40% of the operations executed per training point of discrete mountain car).
Here the same Threefry-2x32 hash (Salmon et al. 2011, 20 rounds; the function
``jax.random`` uses) is written out unrolled, so a draw of any size is one elementwise fusion.

Keys are ordinary JAX PRNG keys (raw ``uint32 (2,)`` as from ``jax.random.PRNGKey``, or typed
keys). The streams differ from ``jax.random``'s (counters are hashed differently), so use a
key either here or with ``jax.random``, not both, to keep draws independent: split first.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

_ROTATIONS = ((13, 15, 26, 6), (17, 29, 16, 24))
_PARITY = np.uint32(0x1BD11BDA)
#: Second counter word of ``fold_in`` (``bits`` uses 0): keeps the two uses apart.
_FOLD_TAG = np.uint32(0x9E3779B9)


def key_data(key: jax.Array) -> jax.Array:
    """uint32 (2,) data of a raw or typed JAX PRNG key."""
    if jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    return jnp.asarray(key, jnp.uint32).reshape((2,))


def _rotl(x: jax.Array, r: int) -> jax.Array:
    return (x << np.uint32(r)) | (x >> np.uint32(32 - r))


def threefry2x32(key: jax.Array, x0: jax.Array, x1: jax.Array):
    """Threefry-2x32 (20 rounds) of the counter pairs (x0, x1) (uint32, same shape) under
    ``key`` (uint32 (2,)) -> (y0, y1). Unrolled: one fusion however large the arrays."""
    ks = (key[0], key[1], key[0] ^ key[1] ^ _PARITY)
    x0 = x0 + ks[0]
    x1 = x1 + ks[1]
    for block in range(5):
        for r in _ROTATIONS[block % 2]:
            x0 = x0 + x1
            x1 = _rotl(x1, r) ^ x0
        x0 = x0 + ks[(block + 1) % 3]
        x1 = x1 + ks[(block + 2) % 3] + np.uint32(block + 1)
    return x0, x1


def fold_in(key: jax.Array, data) -> jax.Array:
    """A new key (uint32 (2,)) from ``key`` and an integer ``data`` (e.g. a step counter); keys
    for different ``data`` are independent. Vmaps over ``key`` and ``data``."""
    d = jnp.asarray(data).astype(jnp.uint32)
    y0, y1 = threefry2x32(key_data(key), d, jnp.full_like(d, _FOLD_TAG))
    return jnp.stack([y0, y1], axis=-1)


def bits(key: jax.Array, n: int) -> jax.Array:
    """n pseudo-random uint32 words from ``key``: uint32 (n,)."""
    half = (n + 1) // 2
    c = jnp.arange(half, dtype=jnp.uint32)
    y0, y1 = threefry2x32(key_data(key), c, jnp.zeros_like(c))
    return jnp.concatenate([y0, y1])[:n]


def uniform(key: jax.Array, n: int) -> jax.Array:
    """n independent draws from U[0, 1): float32 (n,) (24 random bits each)."""
    return (bits(key, n) >> np.uint32(8)).astype(jnp.float32) * jnp.float32(2.0 ** -24)


def normal_from_uniform(u0: jax.Array, u1: jax.Array) -> jax.Array:
    """Standard normal draws from pairs of U[0, 1) draws (Box-Muller)."""
    r = jnp.sqrt(-2.0 * jnp.log1p(-u0))          # 1 - u0 in (0, 1]: finite
    return r * jnp.cos(jnp.float32(2.0 * np.pi) * u1)
