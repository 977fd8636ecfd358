"""``computed_once``: keep XLA from recomputing a small value inside every element of a loop.

XLA's CPU backend fuses cheap producers into their consumers by duplicating them: a scalar
made by a chain of cheap operations and broadcast against an array of R entries is
recomputed for each of the R entries, in every fusion that uses it (e.g. the cell key of a
new point in ``index.note_write``). ``jax.lax.optimization_barrier`` does not help: XLA
removes it before fusion.

``computed_once(x)`` passes x through an operation XLA does not fuse into its consumers: a
reduce-window of stride 2 over the pair [x, lowest value of the dtype]. The producer chain
then runs once, in its own small kernel. Should a future XLA simplify it away, results stay
the same and only the saving is lost.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def computed_once(x: jax.Array) -> jax.Array:
    """x (any shape, numeric or bool dtype) unchanged, bit for bit (NaN, -0.0 included),
    computed once in its own kernel rather than inside every consumer. Works under ``vmap``
    and ``grad``."""
    x = jnp.asarray(x)
    if x.dtype == jnp.bool_:
        return computed_once(x.astype(jnp.int32)) != 0
    low = -jnp.inf if jnp.issubdtype(x.dtype, jnp.floating) \
        else jnp.iinfo(x.dtype).min
    # max(x, lowest) over a window of two: x again (NaN stays NaN, -0.0 stays -0.0).
    pair = jnp.stack([x, jnp.full_like(x, low)])
    ones = (1,) * x.ndim
    return jax.lax.reduce_window(pair, jnp.array(low, x.dtype), jax.lax.max, (2,) + ones,
                                 (2,) + ones, "VALID")[0]
