"""Control flow that stays cheap under ``vmap``: ``masked_fori_loop`` and ``batch_cond``.

``jax.lax.fori_loop(0, n, ...)`` with a batched trip count ``n`` (vmapped seeds, each with its
own episode length) runs until every member is done and after every trip selects between
the new and the old carry of every member: a pass over the whole carry (a HEDGER memory of
10^4-10^6 slots) per trip, far dearer than the step. ``masked_fori_loop`` runs one loop of
``max(n)`` trips and tells the body which members are still active; the body masks its own
writes (cheap: a training step with ``valid=False`` already writes nothing).

``lax.cond`` with a batched predicate runs both branches for every member; ``batch_cond``
runs the true branch only when some member needs it (optionally for those members only).

Both are ``custom_vmap`` functions whose batching rules apply again at every nested ``vmap``
level, and give each member exactly the result of the plain loop or cond.
"""
from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap
from jax.extend.core import ClosedJaxpr, Jaxpr, jaxpr_as_fun


def masked_fori_loop(n: jax.Array, body: Callable[[jax.Array, Any, jax.Array], Any],
                     carry: Any) -> Any:
    """``for i in range(n): carry = body(i, carry, active)``, cheap under ``vmap``.

    n: int () trip count (traced or static, >= 0); body(i int32 (), carry, active bool ()) ->
    carry of the same structure, which must be unchanged where ``active`` is False; carry: a
    pytree. Unbatched it is a plain ``fori_loop`` with ``active`` True; under ``vmap`` with a
    batched n, one loop of max(n) trips, each member active while i < its own n.
    """
    fn, consts = _hoist_closure(body, carry)
    return _loop(fn)(jnp.asarray(n, jnp.int32), carry, consts)


def _consts_as_arguments(closed: ClosedJaxpr) -> Callable:
    """A function of (*consts, *args) that evaluates ``closed`` with its constants passed in."""
    j = closed.jaxpr
    info = j.debug_info
    if info is not None and info.arg_names is not None:
        info = info._replace(arg_names=("const",) * len(j.constvars) + tuple(info.arg_names))
    lifted = Jaxpr(constvars=(), invars=list(j.constvars) + list(j.invars), outvars=j.outvars,
                   eqns=j.eqns, effects=j.effects, debug_info=info)
    return jaxpr_as_fun(ClosedJaxpr(lifted, ()))


def _hoist_closure(body: Callable, carry: Any):
    """``body`` as ``fn(i, carry, active, *consts)`` with every value it closes over (traced or
    not, any dtype) passed explicitly, so that the batching rule sees which are batched
    (``jax.closure_convert`` hoists only float tracers)."""
    example = (jnp.zeros((), jnp.int32), carry, jnp.ones((), bool))
    flat, in_tree = jax.tree_util.tree_flatten(example)
    carry_tree = jax.tree_util.tree_structure(carry)

    def flat_body(*leaves):
        out = body(*jax.tree_util.tree_unflatten(in_tree, leaves))
        out_leaves, out_tree = jax.tree_util.tree_flatten(out)
        if out_tree != carry_tree:
            raise TypeError(f"masked_fori_loop: body returned {out_tree}, expected the carry's "
                            f"structure {carry_tree}")
        return out_leaves

    closed = jax.make_jaxpr(flat_body)(*flat)
    run = _consts_as_arguments(closed)

    def fn(i, c, active, *consts):
        leaves = jax.tree_util.tree_leaves((i, c, active))
        return jax.tree_util.tree_unflatten(carry_tree, run(*consts, *leaves))

    return fn, list(closed.consts)


def _loop(fn: Callable) -> Callable:
    """The custom-vmap loop for a closure-converted body ``fn(i, carry, active, *consts)``."""

    @custom_vmap
    def loop(n, carry, consts):
        def step(i, c):
            return fn(i, c, jnp.ones((), bool), *consts)

        return jax.lax.fori_loop(0, n, step, carry)

    @loop.def_vmap
    def loop_vmap(axis_size, in_batched, n, carry, consts):
        n_b, carry_b, consts_b = in_batched
        # Every member's carry leaf gets the batch axis (members diverge).
        carry = jax.tree_util.tree_map(
            lambda x, b: x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x)),
            carry, carry_b)
        consts_axes = [0 if b else None for b in consts_b]
        vfn = jax.vmap(fn, in_axes=(None, 0, 0, *consts_axes))
        if not n_b:
            def step(i, c):
                return vfn(i, c, jnp.ones((axis_size,), bool), *consts)

            return jax.lax.fori_loop(0, n, step, carry), jax.tree_util.tree_map(
                lambda _: True, carry)
        n_max = jnp.max(n)

        def body(i, c, active):
            return vfn(i, c, active & (i < n), *consts)

        # The same masked loop one level up: an outer vmap (e.g. a hyper-parameter sweep
        # around a seed sweep) batches n_max and gets the same treatment.
        out = masked_fori_loop(n_max, body, carry)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return loop


def batch_cond(pred: jax.Array, true_fn: Callable[[Any], Any], false_fn: Callable[[Any], Any],
               operand: Any, *, compact: int = 0, equal: bool = False) -> Any:
    """``lax.cond(pred, true_fn, false_fn, operand)`` that stays cheap under ``vmap``.

    ``lax.cond`` with a batched predicate runs both branches for every member and selects.
    Here, under ``vmap``, the true branch runs only when *some* member's predicate holds;
    otherwise only the false branch runs. Meant for a rare, expensive branch such as merging
    a memory's neighbour index. Per-member results are exactly those of ``lax.cond``; nested
    ``vmap`` gets the same treatment at every level.

    compact (static int): 0 -- the true branch, when it runs, runs for every member (then
    selected per member). G > 0 -- only the members whose predicate holds run it, gathered
    G at a time and scattered back: for a branch that few members of a large batch need. A
    batch of at most G members uses groups of min(G, ``_SMALL_GROUP``) and runs whole when
    it has no more members than that.

    equal (static bool): the branches give the same results (the true one is a shortcut),
    so under ``vmap`` with a batched predicate only the false branch runs, for every member.
    """
    tfn, tconsts = _hoist_branch(true_fn, operand)
    ffn, fconsts = _hoist_branch(false_fn, operand)
    return _cond(tfn, ffn, int(compact), bool(equal))(jnp.asarray(pred, bool), operand,
                                                       tconsts, fconsts)


def _hoist_branch(fn: Callable, operand: Any):
    """``fn`` as ``g(operand, *consts)`` with its closed-over values explicit (see
    ``_hoist_closure``)."""
    flat, in_tree = jax.tree_util.tree_flatten(operand)
    out_tree = []

    def flat_fn(*leaves):
        out = fn(jax.tree_util.tree_unflatten(in_tree, leaves))
        out_leaves, tree = jax.tree_util.tree_flatten(out)
        out_tree.append(tree)
        return out_leaves

    closed = jax.make_jaxpr(flat_fn)(*flat)
    run = _consts_as_arguments(closed)

    def g(op, *consts):
        return jax.tree_util.tree_unflatten(out_tree[0],
                                            run(*consts, *jax.tree_util.tree_leaves(op)))

    return g, list(closed.consts)


def _compacted(axis_size: int, group: int, pred, operand, vt, tconsts, tc_b, falses):
    """The true branch for the members where ``pred`` bool (axis_size,) holds, ``group`` at a
    time, written over ``falses`` (the false branch's results, leading axis axis_size)."""
    n_pad = -(-axis_size // group) * group
    lanes = jnp.arange(axis_size, dtype=jnp.int32)
    # ids[j]: the j-th member whose predicate holds; axis_size (dropped on write) beyond them.
    slot = jnp.where(pred, jnp.cumsum(pred.astype(jnp.int32)) - 1, n_pad)
    ids = jnp.full((n_pad,), axis_size, jnp.int32).at[slot].set(lanes, mode="drop")
    n_groups = (jnp.sum(pred.astype(jnp.int32)) + group - 1) // group

    def body(g, out):
        sel = jax.lax.dynamic_slice(ids, (g * group,), (group,))
        take = jnp.minimum(sel, axis_size - 1)               # padding: any member, dropped
        op_g = jax.tree_util.tree_map(lambda x: x[take], operand)
        tc_g = [c[take] if b else c for c, b in zip(tconsts, tc_b)]
        res = vt(op_g, *tc_g)
        return jax.tree_util.tree_map(lambda o, r: o.at[sel].set(r, mode="drop"), out, res)

    return jax.lax.fori_loop(0, n_groups, body, falses)


#: Largest group of ``batch_cond(..., compact=G)`` in a batch of at most G members; a batch
#: no larger than this runs the branch whole, where gathering would save nothing.
_SMALL_GROUP = 4


def _cond(tfn: Callable, ffn: Callable, compact: int = 0, equal: bool = False) -> Callable:
    """The custom-vmap cond for hoisted branches ``tfn(operand, *tconsts)``, ``ffn(...)``."""
    @custom_vmap
    def cond(pred, operand, tconsts, fconsts):
        return jax.lax.cond(pred, lambda o: tfn(o, *tconsts), lambda o: ffn(o, *fconsts),
                            operand)

    @cond.def_vmap
    def cond_vmap(axis_size, in_batched, pred, operand, tconsts, fconsts):
        p_b, op_b, tc_b, fc_b = in_batched
        operand = jax.tree_util.tree_map(
            lambda x, b: x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x)),
            operand, op_b)
        vt = jax.vmap(tfn, in_axes=(0, *[0 if b else None for b in tc_b]))
        vf = jax.vmap(ffn, in_axes=(0, *[0 if b else None for b in fc_b]))
        if not p_b:
            out = jax.lax.cond(pred, lambda o: vt(o, *tconsts), lambda o: vf(o, *fconsts),
                               operand)
            return out, jax.tree_util.tree_map(lambda _: True, out)
        if equal:
            out = jax.vmap(ffn, in_axes=(0, *[0 if b else None for b in fc_b]),
                           axis_size=axis_size)(operand, *fconsts)
            return out, jax.tree_util.tree_map(lambda _: True, out)

        group = compact if axis_size > compact else min(compact, _SMALL_GROUP)
        if compact and axis_size > group:
            # (A loop of zero trips when no member needs the branch; under an outer vmap the
            # trip count is batched like any loop's.)
            out = _compacted(axis_size, group, pred, operand, vt, tconsts, tc_b,
                             vf(operand, *fconsts))
            return out, jax.tree_util.tree_map(lambda _: True, out)

        def some(o):
            a, b = vt(o, *tconsts), vf(o, *fconsts)
            return jax.tree_util.tree_map(
                lambda x, y: jnp.where(pred.reshape((axis_size,) + (1,) * (x.ndim - 1)), x, y),
                a, b)

        # Again through batch_cond, so an outer vmap gets the same treatment.
        out = batch_cond(jnp.any(pred), some, lambda o: vf(o, *fconsts), operand)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return cond
