"""Algorithm 1: HEDGER prediction (neighbours -> IVH -> locally weighted regression)."""
from __future__ import annotations

from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from hedger_jax.config import HedgerConfig
from hedger_jax.data_bandwidth import with_data_bandwidth
from hedger_jax.params import HedgerParams, constant, flag, from_fit_space, resolve
from hedger_jax.validation import expect
from hedger_jax.lwr import kernel_weights, local_fit_columns
from hedger_jax.memory import (Memory, Neighbours, scale_inputs, select_neighbours,
                               squared_distances)


class Prediction(NamedTuple):
    """One prediction with the neighbour set it used (k = ``max_neighbours``).

    value:        float32 () Q(s, a), or ``default_value`` when not known.
    known:        bool () enough neighbours and (with ``use_ivh``) inside their hull.
    n_neighbours: int32 () |K|, the neighbours within ``k_thresh`` (at most k).
    indices:      int32 (k,) memory slots of K (meaningless where ``mask`` is False).
    weights:      float32 (k,) kernel weights kappa_i (0 where masked).
    mask:         bool (k,) which entries of ``indices`` are real neighbours.
    """

    value: jax.Array
    known: jax.Array
    n_neighbours: jax.Array
    indices: jax.Array
    weights: jax.Array
    mask: jax.Array


def predict_scaled(config: HedgerConfig, memory: Memory, z: jax.Array,
                   params: Optional[HedgerParams] = None) -> Prediction:
    """Algorithm 1 for a scaled query z (d,) -> ``Prediction`` (see ``predict_detailed``).
    params: ``HedgerParams``, or None for the config's values."""
    return predict_from_neighbours(config, memory, z, select_neighbours(config, memory, z, params),
                                   params)


def predict_from_neighbours(config: HedgerConfig, memory: Memory, z: jax.Array,
                            nb: Neighbours, params: Optional[HedgerParams] = None) -> Prediction:
    """Algorithm 1 for a scaled query z (d,) whose neighbour set K is given (``nb``, in the
    canonical order ``select_neighbours`` returns): the kernel weights, the IVH test and the
    local fit -> ``Prediction``. Known iff at least ``k_min`` neighbours, a finite fit and
    (with ``use_ivh``) the query inside their hull. params: ``HedgerParams``, or None for
    the config's values."""
    p = resolve(config, params)
    zt, w = neighbour_design(memory, z, nb, p)
    y = memory.values[nb.indices]
    fit = local_fit_columns(zt, y, w, nb.mask, ridge=p.ridge, ivh_tol=p.ivh_tol)
    fit = fit._replace(value=from_fit_space(p, clip_to_neighbour_values(p, fit.value, y,
                                                                        nb.mask)))
    count = jnp.sum(nb.mask).astype(jnp.int32)
    known = (count >= p.k_min) & jnp.isfinite(fit.value)
    known = flag(p.use_ivh, known & fit.inside, known)
    value = jnp.where(known, fit.value, jnp.float32(p.default_value))
    return Prediction(value, known, count, nb.indices, w, nb.mask)


def neighbour_design(memory: Memory, z: jax.Array, nb: Neighbours, p: HedgerParams):
    """The local fit's inputs for query z (d,) and its set ``nb``: (zt float32 (d, k) the
    neighbours centred on the query, zero where masked; w float32 (k,) kernel weights)."""
    # Feature-major (d, k), centred on the query: the gathered columns as they come, and the
    # layout whose sums over K XLA vectorises.
    zt = memory.points[:, nb.indices] - z[:, None]
    zt = jnp.where(nb.mask[None, :], zt, 0.0)
    # Distances recomputed from the gathered points (one formula whatever the search method
    # computed), so brute force and the grid index give bit-identical fits.
    sqdist = squared_distances(zt, jnp.zeros((zt.shape[0],), zt.dtype))
    return zt, kernel_weights(sqdist, p.bandwidth, nb.mask)


def clip_to_neighbour_values(p: HedgerParams, value: jax.Array, y: jax.Array,
                             mask: jax.Array) -> jax.Array:
    """The fit's value () clipped to [min, max] of the neighbours' stored values y (k,)
    where mask (k,) holds, with ``clip_to_neighbours``; unchanged without (a constant False:
    not in the program). No neighbours: unchanged (the prediction is not known anyway)."""
    if constant(p.clip_to_neighbours) is False:
        return value
    lo = jnp.min(jnp.where(mask, y, jnp.inf))
    hi = jnp.max(jnp.where(mask, y, -jnp.inf))
    clipped = jnp.where(jnp.any(mask), jnp.clip(value, lo, hi), value)
    return jnp.where(jnp.asarray(p.clip_to_neighbours, bool), clipped, value)


def predict_detailed(config: HedgerConfig, memory: Memory, state: jax.Array,
                     action: jax.Array, params: Optional[HedgerParams] = None) -> Prediction:
    """Algorithm 1 for one query: state (S,), action (A,) -> ``Prediction``.

    params: ``HedgerParams`` (traced hyperparameters), or None for the config's values.
    Vmap it over queries, candidate actions, memories (seeds) or params (settings). Shapes
    are checked when traced (``InvalidInputError`` naming the argument). A NaN or inf in
    the query finds no neighbour: the prediction is "don't know" (``default_value``).
    """
    expect("state", state, (config.state_dim,))
    expect("action", action, (config.action_dim,))
    params = with_data_bandwidth(config, memory, params)
    return predict_scaled(config, memory, scale_inputs(config, state, action, params), params)


def predict(config: HedgerConfig, memory: Memory, state: jax.Array, action: jax.Array,
            params: Optional[HedgerParams] = None):
    """Q(s, a): state (S,), action (A,) -> (value f32 (), known bool (), n_neighbours i32 ()).

    ``predict_detailed`` without the neighbour set; params likewise (None: the config's)."""
    p = predict_detailed(config, memory, state, action, params)
    return p.value, p.known, p.n_neighbours
