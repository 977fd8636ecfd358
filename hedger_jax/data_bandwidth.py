"""The kernel bandwidth chosen from the stored data (beyond the paper): ``bandwidth_k``.

With ``HedgerParams.bandwidth_k`` = m > 0 the kernel bandwidth is not the given
``bandwidth`` h but a width read from the memory. A pool of ``POOL`` stored points spread
evenly over the filled slots (every point while fewer are stored) stands for the data; for
``SAMPLE`` pool points spread evenly over it, the width that gives the point's m-th nearest
pool point (itself included) the weight ``min_weight`` is d_m / sqrt(ln(1 / min_weight)).
The width is the lower median of those (with ``bandwidth_shrink``, times
(size / ``RATE_FROM``)^(-1 / (d + 4)) once more than ``RATE_FROM`` points are stored), at
most h * ``kernel_range`` (the grid index is
built for that radius). An empty memory keeps h. Predictions then use the paper's fixed
kernel at that width.

So the kernel spans a fixed fraction of the data (m / POOL, like LOESS's span) once the
memory holds more than POOL points: the width does not shrink as a memory of one
distribution fills, as the m-th neighbour among all stored points does (size^(-1/d)).
With ``bandwidth_shrink`` it shrinks beyond ``RATE_FROM`` points at size^(-1/(d+4)), the
rate of the asymptotically best width of a local-linear fit in d inputs (Ruppert & Wand
1994). Measured: it helps continuous actions from random starts (the pool's points spread
over the action too, which doubles the width) and hurts discrete ones.

One width for the whole memory, not one per query: per-query widths make the fit's
smoothing differ between the candidate actions the max compares (docs/adaptive-kernel.md).

The public entry points that take a memory and params (``predict``, ``greedy_action``,
``train_step``, ``train_prefix``, ``training_act``, ``evaluate``, ...) call
``with_data_bandwidth`` first; it returns params with ``bandwidth_k`` = 0 (a Python 0), so
the calls they make inside find nothing left to do. A training loop therefore reads the
width once per episode from the memory it acts with.
"""
from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from hedger_jax.config import BANDWIDTH_POOL, HedgerConfig
from hedger_jax.memory import Memory
from hedger_jax.params import HedgerParams, resolve

#: Stored points, spread evenly over the filled slots, that the neighbours are counted among:
#: the kernel spans a fixed fraction of the data (m / POOL), not a fixed number of points.
POOL = BANDWIDTH_POOL
#: Points of the pool (spread evenly over it) whose m-th-neighbour widths the median is over.
SAMPLE = 64
#: Stored points from which the width shrinks at the local-linear rate size^(-1/(d+4)):
#: 16 pools, about the largest memories the span m = 4 was chosen on (the Figure-2
#: protocol ends at 14,500-18,500 points; docs/adaptive-kernel.md).
RATE_FROM = 16 * POOL
#: The float32 +inf bit pattern: the upper end of the search over squared distances.
_INF_BITS = 0x7F800000


def _is_off(p: HedgerParams) -> bool:
    """Whether the bandwidth is the given one for sure (a ``bandwidth_k`` known to be 0:
    a number or a concrete array, not a traced value)."""
    if isinstance(p.bandwidth_k, jax.core.Tracer):
        return False
    return not np.any(np.asarray(p.bandwidth_k))


def pool_slots(size: jax.Array) -> tuple:
    """(pool slots (POOL,), valid (POOL,), sample positions in the pool (SAMPLE,)) for a
    memory holding ``size`` points: every slot while size <= POOL, else POOL slots spread
    evenly over [0, size); the sample spread evenly over the valid pool."""
    span = jnp.maximum(size, POOL).astype(jnp.float32)
    slots = jnp.floor((jnp.arange(POOL, dtype=jnp.float32) + 0.5) * span / POOL)
    slots = slots.astype(jnp.int32)
    n_pool = jnp.minimum(size, POOL).astype(jnp.float32)
    rows = jnp.floor((jnp.arange(SAMPLE, dtype=jnp.float32) + 0.5) * n_pool / SAMPLE)
    return slots, slots < size, jnp.clip(rows.astype(jnp.int32), 0, POOL - 1)


def median_mth_sqdist(points: jax.Array, valid: jax.Array, rows: jax.Array,
                      m: jax.Array) -> jax.Array:
    """The lower median over the ``rows`` (SAMPLE,) of the pool ``points`` (d, POOL) of each
    row's squared distance to its m-th nearest valid pool point (itself included); +inf
    where fewer than half the rows have m valid points. Exact: a bisection over the float32
    bit patterns (monotone for non-negative floats) of the one threshold t at which half
    the rows have m points within t; no sort (a (SAMPLE, POOL) sort costs 30x more)."""
    q = points[:, rows]
    d2 = jnp.sum((q[:, :, None] - points[:, None, :]) ** 2, axis=0)      # (SAMPLE, POOL)
    bits = jnp.where(valid[None, :], jax.lax.bitcast_convert_type(d2, jnp.int32), _INF_BITS)
    need = SAMPLE // 2

    def halve(_, lo_hi):
        lo, hi = lo_hi
        mid = lo + (hi - lo) // 2
        enough = jnp.sum(jnp.sum(bits <= mid, axis=1) >= m) >= need
        return jnp.where(enough, lo, mid + 1), jnp.where(enough, mid, hi)

    _, hi = jax.lax.fori_loop(0, 31, halve, (jnp.int32(0), jnp.int32(_INF_BITS)))
    return jax.lax.bitcast_convert_type(hi, jnp.float32)


def data_bandwidth(config: HedgerConfig, memory: Memory,
                   params: Optional[HedgerParams] = None) -> jax.Array:
    """The width () the module doc describes (``params.bandwidth`` where ``bandwidth_k`` is
    0 or the memory is empty). params: ``HedgerParams`` or None (the config's values)."""
    p = resolve(config, params)
    h0 = jnp.asarray(p.bandwidth, jnp.float32)
    widest = h0 * jnp.asarray(p.kernel_range, jnp.float32)
    size = memory.size
    slots, valid, rows = pool_slots(size)
    pool = memory.points[:, jnp.clip(slots, 0, memory.points.shape[-1] - 1)]
    d2_m = median_mth_sqdist(pool, valid, rows, jnp.asarray(p.bandwidth_k, jnp.int32))
    log_inv = jnp.log(1.0 / jnp.asarray(p.min_weight, jnp.float32))
    shrink = (jnp.maximum(size, RATE_FROM).astype(jnp.float32) / RATE_FROM) ** (
        -1.0 / (memory.points.shape[0] + 4))
    shrink = jnp.where(jnp.asarray(p.bandwidth_shrink), shrink, 1.0)
    h = jnp.minimum(jnp.sqrt(d2_m / log_inv) * shrink, widest)
    return jnp.where((size > 0) & (p.bandwidth_k > 0) & (h > 0), h, h0)


def with_data_bandwidth(config: HedgerConfig, memory: Memory,
                        params: Optional[HedgerParams]) -> Optional[HedgerParams]:
    """params with the data-chosen bandwidth filled in: unchanged (None stays None) where
    ``bandwidth_k`` is a constant 0, else params with ``bandwidth`` = ``data_bandwidth``,
    ``bandwidth_k`` = 0 (a Python 0) and ``k_thresh`` the selection radius at that width."""
    p = resolve(config, params)
    if _is_off(p):
        return params
    on = jnp.asarray(p.bandwidth_k) > 0
    h = data_bandwidth(config, memory, params)
    radius = jnp.where(on, h * jnp.sqrt(jnp.log(1.0 / jnp.asarray(p.min_weight, jnp.float32))),
                       p.k_thresh)
    return p._replace(bandwidth=h, bandwidth_k=0, k_thresh=radius)
