"""The kernel bandwidth chosen from the stored data (beyond the paper): ``bandwidth_k``.

With ``HedgerParams.bandwidth_k`` = m > 0 the kernel bandwidth is not the given
``bandwidth`` h but a width read from the memory: the median, over ``SAMPLE`` stored points
spread evenly over the filled slots, of the width that gives a point's m-th nearest stored
point (itself included) the weight ``min_weight``, d_m / sqrt(ln(1 / min_weight)). A
point with fewer than m stored points within the widest selection radius (at h *
``kernel_range``) counts as that widest width, and the median is kept at most h *
``kernel_range`` (the grid index is built for that radius). An empty memory keeps h.
Predictions then use the paper's fixed kernel at that width.

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

from hedger_jax.config import HedgerConfig
from hedger_jax.memory import Memory, select_neighbours
from hedger_jax.params import HedgerParams, resolve

#: Stored points the median is taken over.
SAMPLE = 128


def _is_off(p: HedgerParams) -> bool:
    """Whether the bandwidth is the given one for sure (a ``bandwidth_k`` known to be 0:
    a number or a concrete array, not a traced value)."""
    if isinstance(p.bandwidth_k, jax.core.Tracer):
        return False
    return not np.any(np.asarray(p.bandwidth_k))


def data_bandwidth(config: HedgerConfig, memory: Memory,
                   params: Optional[HedgerParams] = None) -> jax.Array:
    """The width () the module doc describes (``params.bandwidth`` where ``bandwidth_k`` is
    0 or the memory is empty). params: ``HedgerParams`` or None (the config's values)."""
    p = resolve(config, params)
    h0 = jnp.asarray(p.bandwidth, jnp.float32)
    widest = h0 * jnp.asarray(p.kernel_range, jnp.float32)
    size = memory.size
    # Slots spread evenly over [0, size): a deterministic sample, so every call on the same
    # memory gives the same width.
    i = jnp.arange(SAMPLE, dtype=jnp.float32)
    slots = jnp.floor((i + 0.5) * size.astype(jnp.float32) / SAMPLE).astype(jnp.int32)
    slots = jnp.clip(slots, 0, jnp.maximum(size - 1, 0))
    log_inv = jnp.log(1.0 / jnp.asarray(p.min_weight, jnp.float32))

    def width(z):
        nb = select_neighbours(config, memory, z, params)   # radius: k_thresh, the widest
        d2 = jnp.where(nb.mask, nb.sqdist, jnp.inf)
        # The m-th smallest without a sort: the least d2_i with at least m entries <= it.
        at_or_below = jnp.sum((d2[None, :] <= d2[:, None]).astype(jnp.int32), axis=1)
        d2_m = jnp.min(jnp.where(at_or_below >= p.bandwidth_k, d2, jnp.inf))
        return jnp.minimum(jnp.sqrt(d2_m / log_inv), widest)

    h = jnp.minimum(jnp.median(jax.vmap(width)(memory.points[:, slots].T)), widest)
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
    if params is None:    # the config's values: the (d,) input scaling as arrays, as given
        p = p._replace(input_offset=jnp.asarray(p.input_offset, jnp.float32),
                       input_scale=jnp.asarray(p.input_scale, jnp.float32))
    # kernel_k stays as it is: it is 0 wherever bandwidth_k > 0 (check_params).
    return p._replace(bandwidth=h, bandwidth_k=0, k_thresh=radius)
