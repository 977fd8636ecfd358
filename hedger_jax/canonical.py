"""K's canonical order: real neighbours by slot, then padding in its own order.

Every search method (brute force, the grid index's paths) hands its neighbour set to the
fit in this order, so fits are bit-identical whichever found K (float32 sums depend on the
order of their terms).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

#: Padding keys end here: above every slot (int32 slot indices).
CANON_PAD = int(np.iinfo(np.int32).max)


def canonical_order(idx: jax.Array, d2: jax.Array, mask: jax.Array):
    """idx int32 (w,), d2 float32 (w,), mask bool (w,) -> (idx (w,), d2 (w,), mask (w,)): the
    real entries (``mask``; their slots are distinct) by ascending slot, then the others in
    their given order; the new mask is a prefix as long as the real count.

    Exact (a permutation, no arithmetic on the values). On the first w' entries of a longer
    set whose later entries are all padding it gives the same result as on the whole set.
    """
    w = idx.shape[-1]
    j = jnp.arange(w, dtype=jnp.int32)
    # Distinct keys: a real neighbour's slot, else one of the w largest int32 by position.
    key = jnp.where(mask, idx.astype(jnp.int32), CANON_PAD - w + j)
    # Ranks by a w x w comparison count and a one-hot selection (exact: one nonzero term per
    # sum): both fuse and vectorise, where a sort is a call per query and a CPU scatter a loop.
    rank = jnp.sum((key[None, :] < key[:, None]).astype(jnp.int32), axis=1)
    hit = rank[None, :] == j[:, None]                          # (w out, w in)
    idx, d2 = (jnp.sum(jnp.where(hit, a[None, :], jnp.zeros((), a.dtype)), axis=1)
               for a in (idx, d2))
    return idx, d2, j < jnp.sum(mask.astype(jnp.int32))
