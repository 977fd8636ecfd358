"""Greedy action search: max_a Q(s, a) over a discrete set or a continuous interval.

Continuous actions use the paper's search (after Brent 1973): ``greedy_samples`` evenly spaced
actions over the bounds, then successive parabolic interpolation through the best sample and
its two neighbours, sampling at the fitted maximum, until two successive maxima are closer
than ``greedy_tol`` or ``greedy_iters`` refinements were made (a ``lax.while_loop``, so it
jits and vmaps). The answer is always the best *evaluated* sample, so it never leaves the
bounds and is never worse than the initial grid.

"Don't know" handling: an unknown candidate counts as ``default_value`` (as a table
initialised with that value would); if every evaluated candidate is unknown the greedy policy
acts at random (``known`` is False), as the paper does. With ``guess_unknown`` (beyond the
paper) it first guesses: the same search over the local fits without the hull check (at
least ``k_min`` neighbours within the kernel are still needed). Only where those know nothing
either is the action random. The value stays ``default_value`` and ``known`` False: the guess
steers the policy, never a training target (``greedy_value``).

Every function taking ``params`` accepts a ``HedgerParams`` (traced hyperparameters) or None
for the config's values.
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from hedger_jax.config import HedgerConfig
from hedger_jax.data_bandwidth import with_data_bandwidth
from hedger_jax.memory import Memory
from hedger_jax.params import constant, resolve
from hedger_jax.validation import expect, expect_key
from hedger_jax.prediction import Prediction, predict_detailed


class GreedySets(NamedTuple):
    """Neighbour sets a greedy search found (as ``replay_cache`` stores them: the slots of K
    in canonical order, then -1). candidates: int32 (n, k), K of each of
    ``greedy_candidates``; chosen: int32 (k,), K of the action taken; has_chosen: bool (),
    whether ``chosen`` is known (not for a random action taken when nothing was known)."""

    candidates: jax.Array
    chosen: jax.Array
    has_chosen: jax.Array


#: The value of an unfilled sample slot: below every evaluated value.
_NEG = -jnp.inf


def _first_index(hit: jax.Array) -> jax.Array:
    """Index int32 () of the first True of hit (m,) (m if none), by an integer minimum."""
    m = hit.shape[-1]
    return jnp.min(jnp.where(hit, jnp.arange(m, dtype=jnp.int32), m))


def _argmin_nonneg(x: jax.Array) -> jax.Array:
    """``jnp.argmin`` of x (m,) float32 >= 0 or +inf, no NaN -> int32 (): non-negative floats
    order as their bits, so two integer minima (the smallest key, then its first index)
    replace XLA's float argmin, a serial loop with NaN checks. Same index, ties to the first."""
    key = jax.lax.bitcast_convert_type(x, jnp.int32)
    return jnp.minimum(_first_index(key == jnp.min(key)), x.shape[-1] - 1)


def _argmax_float(x: jax.Array) -> jax.Array:
    """``jnp.argmax`` of x (m,) float32 without NaN (-inf allowed) -> int32 (), ties to the
    first: the floats mapped to integers of the same order (-0.0 first made +0.0, as argmax
    sees them equal)."""
    bits = jax.lax.bitcast_convert_type(x + 0.0, jnp.int32)
    key = bits ^ ((bits >> 31) & 0x7FFFFFFF)
    return jnp.minimum(_first_index(key == jnp.max(key)), x.shape[-1] - 1)


def _bracket(xs: jax.Array, fs: jax.Array, filled: jax.Array):
    """Best filled sample and its nearest filled neighbours on each side (at a boundary, the
    two nearest on the side there is).

    xs, fs, filled (m,) -> (three (x, f) pairs with x_l < x_b < x_r where possible, index of
    the best).
    """
    # Integer forms of argmax / argmin (same indices): this runs once per refinement, and
    # XLA's float ones are serial loops with NaN checks.
    fs_m = jnp.where(filled, fs, _NEG)
    b = _argmax_float(fs_m)
    xb = xs[b]
    dist = jnp.abs(xs - xb)
    others = filled & (jnp.arange(xs.shape[0]) != b) & (dist > 0)
    left = others & (xs < xb)
    right = others & (xs > xb)
    big = jnp.inf
    i_l = _argmin_nonneg(jnp.where(left, dist, big))
    i_r = _argmin_nonneg(jnp.where(right, dist, big))
    has_l, has_r = jnp.any(left), jnp.any(right)
    # Second-nearest on the available side, for a best sample at the boundary.
    i_r2 = _argmin_nonneg(jnp.where(right & (jnp.arange(xs.shape[0]) != i_r), dist, big))
    i_l2 = _argmin_nonneg(jnp.where(left & (jnp.arange(xs.shape[0]) != i_l), dist, big))
    i0 = jnp.where(has_l, i_l, jnp.where(has_r, b, i_l))
    i1 = jnp.where(has_l & has_r, b, jnp.where(has_l, i_l, i_r))
    i2 = jnp.where(has_r, jnp.where(has_l, i_r, i_r2), b)
    # When only the left side exists: (l2, l, b); only the right side: (b, r, r2).
    i0 = jnp.where(~has_r & has_l, i_l2, i0)
    return (xs[i0], fs_m[i0]), (xs[i1], fs_m[i1]), (xs[i2], fs_m[i2]), b


def _parabola_vertex(p0, p1, p2):
    """Vertex x () of the parabola through three (x, f) points, and whether it is a maximum
    (bool (); else the vertex is the middle point's x)."""
    (x0, f0), (x1, f1), (x2, f2) = p0, p1, p2
    d01 = jnp.where(x1 != x0, (f1 - f0) / (x1 - x0), 0.0)
    d12 = jnp.where(x2 != x1, (f2 - f1) / (x2 - x1), 0.0)
    c2 = jnp.where(x2 != x0, (d12 - d01) / (x2 - x0), 0.0)
    c1 = d01 - c2 * (x0 + x1)
    concave = (c2 < 0) & jnp.isfinite(c1) & jnp.isfinite(c2)
    vertex = jnp.where(concave, -c1 / (2.0 * jnp.where(concave, c2, -1.0)), x1)
    return vertex, concave


def search_grid(low: float, high: float, n_samples: int) -> jax.Array:
    """The initial samples of ``search_1d``: float32 (n_samples,) evenly spaced in [low, high]."""
    return jnp.linspace(low, high, n_samples, dtype=jnp.float32)


def _break_ties(ties, fs: jax.Array, best: jax.Array, n_samples: int):
    """Equal best values at two or more of the first ``n_samples`` samples: one of them at
    random (while every value is still the same, ties to the first would always take the low
    end). ties: (switch bool (), U[0, 1) draw ()); fs (n,). Returns (best (), whether the
    draw was used (), the drawn sample ())."""
    on, u_tie = ties
    tied = (jnp.arange(fs.shape[0]) < n_samples) & (fs == fs[best])
    count = jnp.sum(tied)
    rank = jnp.minimum((u_tie * count).astype(jnp.int32), count - 1)
    pick = _first_index(tied & (jnp.cumsum(tied) - 1 == rank))
    use = (count >= 2) & on
    return jnp.where(use, pick, best), use, pick


def search_1d(f: Callable[[jax.Array], Tuple[jax.Array, ...]], low: float, high: float,
              n_samples: int, iters: int, tol: float, initial=None, with_count: bool = False,
              with_aux: bool = False, ties=None):
    """Maximise f over [low, high]; f: x () -> (value (), known ()), or with ``with_aux``
    (value (), known (), aux): aux any pytree that f computes along (e.g. a neighbour set).

    ``initial``: optional (values (n_samples,), known (n_samples,)[, aux]) of f at
    ``search_grid(low, high, n_samples)``, when the caller evaluated them in a batch of its own.
    ``ties``: optional (switch bool (), U[0, 1) draw ()): where the switch holds and two or
    more initial samples share the best value, the draw picks one of them.
    Returns (x_best (), f_best (), any_known ()): the best evaluated sample (ties to the
    first, or as ``ties`` says); with ``with_count`` also the number of refinement
    evaluations (int32 (), at most ``iters``); with ``with_aux`` then also (aux of the grid's samples, leading axis
    n_samples; aux of the best sample).
    """
    n_total = n_samples + iters
    grid = search_grid(low, high, n_samples)
    if not with_aux:
        g = f
        f = lambda x: tuple(g(x)) + (None,)  # noqa: E731
    if initial is None:
        # One sample after another: a query searched alone reads its first scan trip by
        # contiguous windows (``index._first_trip``), which a vmapped batch cannot.
        f0, k0, aux0 = jax.lax.map(f, grid)
    else:
        f0, k0 = initial[0], initial[1]
        aux0 = initial[2] if len(initial) > 2 else None
    xs = jnp.zeros((n_total,), jnp.float32).at[:n_samples].set(grid)
    fs = jnp.full((n_total,), _NEG, jnp.float32).at[:n_samples].set(f0)
    filled = jnp.arange(n_total) < n_samples

    def propose(xs, fs, filled):
        """The next sample: the vertex of the parabola through the best sample and its
        neighbours, and whether it is worth evaluating (a maximum, not a sample already
        evaluated: f there is known, and the search would only propose it again)."""
        p0, p1, p2, _ = _bracket(xs, fs, filled)
        vertex, concave = _parabola_vertex(p0, p1, p2)
        vertex = jnp.clip(jnp.clip(vertex, p0[0], p2[0]), low, high)
        return vertex, concave & ~jnp.any(filled & (xs == vertex))

    def body(carry):
        i, xs, fs, filled, prev, vertex, _, any_known, best_f, best_aux = carry
        fv, kv, av = f(vertex)
        slot = n_samples + i
        xs, fs, filled = xs.at[slot].set(vertex), fs.at[slot].set(fv), filled.at[slot].set(True)
        any_known = any_known | kv
        # The best sample so far, as the final argmax picks it (the first of equal maxima).
        better = fv > best_f
        best_f = jnp.where(better, fv, best_f)
        best_aux = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), av, best_aux)
        nxt, worth = propose(xs, fs, filled)
        go = worth & (i + 1 < iters) & ~(jnp.abs(vertex - prev) < tol)
        return (i + 1, xs, fs, filled, vertex, nxt, go, any_known, best_f, best_aux)

    # A while loop, so a search that has converged (or found no concave bracket, e.g. while
    # nothing is known) stops evaluating. A vertex that is no maximum or repeats a sample is
    # not evaluated: the paper's loop would discard it, so the result is the same.
    vertex, worth = propose(xs, fs, filled)
    b0 = _argmax_float(jnp.where(filled, fs, _NEG))
    init = (jnp.zeros((), jnp.int32), xs, fs, filled, jnp.float32(jnp.nan), vertex,
            worth & (iters > 0), jnp.any(k0), fs[b0],
            jax.tree_util.tree_map(lambda a: a[b0], aux0))
    n_evals, xs, fs, filled, _, _, _, any_known, _, best_aux = jax.lax.while_loop(
        lambda c: c[6], body, init)
    best = _argmax_float(jnp.where(filled, fs, _NEG))
    if ties is not None:
        best, use, pick = _break_ties(ties, fs, best, n_samples)
        if with_aux:
            best_aux = jax.tree_util.tree_map(
                lambda a, b: jnp.where(use, a[jnp.minimum(pick, n_samples - 1)], b), aux0, best_aux)
    out = (xs[best], fs[best], any_known) + ((n_evals,) if with_count else ())
    return out + ((aux0, best_aux) if with_aux else ())


def maximise_1d(f: Callable[[jax.Array], jax.Array], low: float, high: float,
                n_samples: int = 11, iters: int = 8, tol: float = 1e-3):
    """Maximise a scalar function f: x () -> () over [low, high] -> (x_best (), f_best ()),
    by the greedy search of continuous actions (module doc)."""
    x, fx, _ = search_1d(lambda x: (f(x), jnp.ones((), bool)), low, high, n_samples, iters, tol)
    return x, fx


def _packed(p: Prediction) -> jax.Array:
    """K's slots, int32 (..., k): the real neighbours (canonical order), then -1."""
    return jnp.where(p.mask, p.indices, -1)


def _discrete_values(config: HedgerConfig, memory: Memory, state: jax.Array, params=None):
    """Every discrete action's prediction: state (S,) -> (actions (n, A), values (n,),
    known (n,), K of each (n, k) as ``_packed``)."""
    actions = jnp.asarray(config.discrete_actions, jnp.float32)          # (n, A)
    params = with_data_bandwidth(config, memory, params)
    p = jax.vmap(lambda a: predict_detailed(config, memory, state, a, params))(actions)
    return actions, p.value, p.known, _packed(p)


def _ties(config: HedgerConfig, params, u_tie):
    """search_1d's ``ties`` (switch, draw): None where there is no draw or ``random_ties`` is
    a constant False (the same program as without the option)."""
    if u_tie is None:
        return None
    on = resolve(config, params).random_ties
    if constant(on) is False:
        return None
    return jnp.asarray(on, bool), u_tie


def _continuous_search(config: HedgerConfig, memory: Memory, state: jax.Array, initial=None,
                       with_aux: bool = False, params=None, u_tie=None):
    """``search_1d`` of Q(state, a) over the action interval (with_aux: K of each sample);
    u_tie: a U[0, 1) draw () for ``random_ties`` (None: ties to the first)."""
    params = with_data_bandwidth(config, memory, params)

    def f(a):
        p = predict_detailed(config, memory, state, a[None], params)
        return (p.value, p.known, _packed(p)) if with_aux else (p.value, p.known)

    return search_1d(f, config.action_low[0], config.action_high[0], config.greedy_samples,
                     config.greedy_iters, config.greedy_tol, initial, with_aux=with_aux,
                     ties=_ties(config, params, u_tie))


def greedy_candidates(config: HedgerConfig) -> jax.Array:
    """The actions (n, A) that ``greedy_value`` evaluates first in one batch: the discrete set,
    or the continuous search's initial grid."""
    if config.is_discrete:
        return jnp.asarray(config.discrete_actions, jnp.float32)
    return search_grid(config.action_low[0], config.action_high[0], config.greedy_samples)[:, None]


def greedy_value_from(config: HedgerConfig, memory: Memory, state: jax.Array,
                      values: jax.Array, known: jax.Array, params=None):
    """``greedy_value`` given Q(state, a) at ``greedy_candidates`` (values, known (n,)),
    evaluated by the caller, e.g. batched with other queries. Same result."""
    if config.is_discrete:
        return jnp.max(values), jnp.any(known)
    _, value, any_known = _continuous_search(config, memory, state, (values, known),
                                             params=params)
    return value, any_known


def greedy_value(config: HedgerConfig, memory: Memory, state: jax.Array, params=None):
    """max_a Q(state, a) as used by training: state (S,) -> (value (), known ()).

    Deterministic (no key). Unknown candidates count as ``default_value``; ``known`` says
    whether any candidate was known. params: ``HedgerParams``, or None for the config's.
    """
    expect("state", state, (config.state_dim,))
    if config.is_discrete:
        _, values, known, _ = _discrete_values(config, memory, state, params)
        return jnp.max(values), jnp.any(known)
    _, value, known = _continuous_search(config, memory, state, params=params)
    return value, known


def greedy_draws(config: HedgerConfig) -> int:
    """How many U[0, 1) draws ``greedy_action_from_uniform`` uses."""
    return len(config.discrete_actions) + 1 if config.is_discrete else config.action_dim


def greedy_action_from_uniform(config: HedgerConfig, memory: Memory, state: jax.Array,
                               u: jax.Array, params=None):
    """``greedy_action`` with its randomness given: u float32 (``greedy_draws(config)``,) of
    U[0, 1) draws (tie-breaks, then the random action when nothing is known)."""
    if config.is_discrete:
        return greedy_choice(config, memory, state, u, params)[:3]
    # Without the neighbour sets, so the search carries none through its loop.
    x, value, any_known = _continuous_search(config, memory, state, params=params, u_tie=u[0])
    x, found = _guess_continuous(config, memory, state, params, u[0], x, any_known)
    return _continuous_choice(config, u, x, value, any_known, found, params=params)


def greedy_choice(config: HedgerConfig, memory: Memory, state: jax.Array, u: jax.Array,
                  params=None):
    """``greedy_action_from_uniform`` and the neighbour sets its search found:
    -> (action (A,), value (), known (), ``GreedySets``) for ``hedger_jax.replay_cache``."""
    if config.is_discrete:
        actions, values, known, sets = _discrete_values(config, memory, state, params)
        n = actions.shape[0]
        pick = _discrete_pick(values, u[:n])
        rand = jnp.minimum((u[n] * n).astype(jnp.int32), n - 1)
        any_known = jnp.any(known)
        on = _guess_switch(config, params)
        if on is not None:
            def search():
                _, g_values, g_known, _ = _discrete_values(
                    config, memory, state, _guess_params(config, memory, params))
                return _discrete_pick(g_values, u[:n]), jnp.any(g_known)

            pick, found = _guess(on, search, pick, any_known)
        else:
            found = any_known
        idx = jnp.where(found, pick, rand)
        # Every action of the set was evaluated: the chosen one's K is known either way.
        return actions[idx], values[idx], any_known, GreedySets(sets, sets[idx],
                                                                jnp.ones((), bool))
    x, value, any_known, sets, best = _continuous_search(config, memory, state, with_aux=True,
                                                         params=params, u_tie=u[0])
    x, found = _guess_continuous(config, memory, state, params, u[0], x, any_known)
    # A random or guessed action (nothing known): its K at the memory's kernel is not known.
    return _continuous_choice(config, u, x, value, any_known, found, params) + (
        GreedySets(sets, best, any_known),)


def _continuous_choice(config: HedgerConfig, u: jax.Array, x, value, any_known, found,
                       params=None):
    """The search's best sample where ``found`` (known, or guessed), else a uniformly random
    action from u (A,); value ``default_value`` unless ``any_known``:
    -> (action (A,), value (), known ())."""
    low = jnp.asarray(config.action_low, jnp.float32)
    high = jnp.asarray(config.action_high, jnp.float32)
    rand = jnp.minimum(low + u * (high - low), high)
    action = jnp.where(found, x[None], rand)
    default = resolve(config, params).default_value
    return action, jnp.where(any_known, value, jnp.float32(default)), any_known


def _guess_switch(config: HedgerConfig, params):
    """``guess_unknown`` as a bool () switch, or None where it is a constant False (the same
    program as without the option)."""
    on = resolve(config, params).guess_unknown
    if constant(on) is False:
        return None
    return jnp.asarray(on, bool)


def _guess_params(config: HedgerConfig, memory: Memory, params):
    """The settings the guess reads the fits with: the memory's kernel without the hull
    check."""
    return resolve(config, with_data_bandwidth(config, memory, params))._replace(use_ivh=False)


def _guess(on, search, choice, found):
    """``search() -> (choice, found)`` where nothing is found and the switch ``on`` holds
    (a ``lax.cond``: a known state pays nothing)."""
    return jax.lax.cond(~found & on, lambda _: search(), lambda _: (choice, found), None)


def _guess_continuous(config: HedgerConfig, memory: Memory, state: jax.Array, params,
                      u_tie, x, any_known):
    """(x, found): the search's best sample, or where it knew nothing the guess (module
    doc) with ``guess_unknown``; found: whether x is known or guessed."""
    on = _guess_switch(config, params)
    if on is None:
        return x, any_known

    def search():
        gx, _, g_known = _continuous_search(config, memory, state, u_tie=u_tie,
                                            params=_guess_params(config, memory, params))
        return gx, g_known

    return _guess(on, search, x, any_known)


def _discrete_pick(values: jax.Array, u: jax.Array) -> jax.Array:
    """The best of the discrete actions' values (n,), ties broken by the draws u (n,)."""
    ties = values >= jnp.max(values)
    return jnp.argmax(jnp.where(ties, u, -1.0))


def greedy_action(config: HedgerConfig, memory: Memory, state: jax.Array, key: jax.Array,
                  params=None):
    """The greedy action: state (S,), key -> (action (A,), value (), known ()).

    Ties among the best discrete actions are broken at random, among the continuous
    search's initial samples with ``random_ties`` (else the first); when nothing is known the
    action is uniformly random (from the set, or in the box; with ``guess_unknown`` guessed
    first, module doc), its value ``default_value``, and ``known`` is False. The randomness
    is one ``jax.random.uniform`` draw of ``greedy_draws(config)`` numbers from ``key``.
    params: ``HedgerParams``, or None for the config's values.
    """
    expect("state", state, (config.state_dim,))
    expect_key("key", key)
    u = jax.random.uniform(key, (greedy_draws(config),))
    return greedy_action_from_uniform(config, memory, state, u, params)
