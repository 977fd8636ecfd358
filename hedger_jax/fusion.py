"""``computed_once``: keep XLA from recomputing a small value inside every element of a loop.

XLA's CPU backend fuses cheap producers into their consumers, *duplicating* them: a scalar
computed by a chain of cheap operations (a dynamic slice, a few multiplies, floors,
conversions) and then broadcast against an array of R entries is recomputed for each of the R
entries, in every fusion that uses it. In ``index.note_write`` the level-0 cell key of the new
point (~30 scalar operations) was recomputed in five O(R) passes (R = 1,024): ~4 us of a
training step's 16 us replay (measured, jax 0.10.2, 2-core CPU).
``jax.lax.optimization_barrier`` does not help: XLA removes it before fusion.

``computed_once(x)`` returns x unchanged (bit for bit), computed by an operation XLA does not
fuse into its consumers (a reduce-window: the maximum of x and the dtype's lowest value over a
window of two): the producer chain is evaluated once, in its own small kernel, and the
consumers read the result. Where a future XLA simplified it away, results would stay the same
and only the saving would be lost.

The pair is reduced with stride 2 (output: x's shape). The earlier form, the first element of
a running maximum over the pair [x, x], computed the producer chain twice (the stacked pair)
and a reduce-window output twice x's size. Paired, bit-identical, 2-core CPU: training 1.06x /
1.15x discrete / continuous at 2e4 slots, 1.22x / 1.07x at 3e5; batched selection 1.16x /
1.08x discrete / continuous at 1e3 slots, 1.04-1.05x at 1e4 and 3e5. A plain reduction over
the pair fused the producer chain into a slow reduction loop (0.80x at 1e3, continuous).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def computed_once(x: jax.Array) -> jax.Array:
    """x (any shape, numeric or bool dtype) unchanged, materialised once (see module doc)."""
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
