"""``computed_once``: keep XLA from recomputing a small value inside every element of a loop.

XLA's CPU backend fuses cheap producers into their consumers, *duplicating* them: a scalar
computed by a chain of cheap operations (a dynamic slice, a few multiplies, floors,
conversions) and then broadcast against an array of R entries is recomputed for each of the R
entries, in every fusion that uses it. In ``index.note_write`` the level-0 cell key of the new
point (~30 scalar operations) was recomputed in five O(R) passes (R = 1,024): ~4 us of a
training step's 16 us replay (measured, jax 0.10.2, 2-core CPU).
``jax.lax.optimization_barrier`` does not help: XLA removes it before fusion.

``computed_once(x)`` returns x unchanged (bit for bit), computed by an operation XLA does not
fuse into its consumers (the first element of a two-element running maximum, a reduce-window):
the producer chain is evaluated once, in its own small kernel, and the consumers read the
result. Cost: one extra operation (~0.1 us). Where a future XLA simplified it away, results
would stay the same and only the saving would be lost.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def computed_once(x: jax.Array) -> jax.Array:
    """x (any shape, numeric or bool dtype) unchanged, materialised once (see module doc)."""
    x = jnp.asarray(x)
    if x.dtype == jnp.bool_:
        return computed_once(x.astype(jnp.int32)) != 0
    return jax.lax.cummax(jnp.stack([x, x]), axis=0)[0]
