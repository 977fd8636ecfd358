"""The k smallest entries of a vector, and exclusive prefix counts, in forms that XLA's CPU
backend can compile -- with the loop around them -- into one kernel.

Why. XLA's CPU runtime runs a program as a sequence of small compiled kernels ("thunks"),
paying ~20-100 ns per kernel call; a HEDGER training step is hundreds of tiny kernels, so
that overhead is most of its cost. XLA can instead compile a whole ``while`` loop into a
single kernel (its "small while loop hoisting", enabled for loops of any size by a flag
that ``hedger_jax.runtime`` adds by default on the CPU; ``HEDGER_JAX_LOOP_KERNELS=0`` leaves it
out), but only a loop that contains no custom call, no sort and no batched matrix product. ``lax.top_k`` is a custom call on the CPU, and the grid scan's
prefix count a (batched) matrix product. So for vmapped batches of fewer than
``BIG_BATCH`` queries (the training step's 1-11 queries, an evaluation's lanes) and for
single queries:

* ``smallest_k`` finds the k-th smallest value by a binary search over the float bits (up
  to 31 counting passes, one reduction each, in a loop the compiler does not unroll), then
  keeps the entries below it and the first ties, compacted in position order: the same set
  as ``lax.top_k`` of the negated values (ties broken by lower position), not sorted.
* ``exclusive_count`` sums within blocks of 16 and over the block totals by masked
  reductions (an associative scan's ladder of slices made the kernels slow to compile).

Without the flag (and with ``smallest_k(kernel_form=False)``), ``lax.top_k`` and the matrix
product are used. Multi-level grids, which select on every scan trip, use the sort-free form
too since LLVM's unroll threshold is lowered with the flag (before, it cost as much as the
kernels saved). Big vmapped batches (e.g. ``predict`` over thousands of
queries) keep them too: they are not compiled into one kernel anyway (XLA splits their large
operations over threads), and there those are faster (measured in ``benchmarks``).
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_batching import custom_vmap

from hedger_jax.runtime import loop_kernels_enabled

#: Vmapped batches of at least this many members use ``lax.top_k`` / a matrix product.
BIG_BATCH = 64
#: Widest vector whose prefix count may be a matrix product (a width^2 float32 constant).
MATMUL_PREFIX_MAX = 256
#: Bits of +inf in float32: the largest key of a non-negative value (NaN counts as +inf).
_INF_BITS = 0x7F800000


def _before(n: int) -> jax.Array:
    """bool (n, n): entry (i, j) is True when j < i.

    Built in the program (iota and compare; XLA folds it into a constant), not as a NumPy
    array: an array constant inside a ``custom_vmap`` function becomes an operand of the
    custom_vmap call, which an enclosing ``lax.cond`` with a batched predicate (one per
    vmapped member) broadcasts -- and JAX's custom_vmap refuses a batched constant (vmapped
    continuous-action training with the grid index failed to trace that way)."""
    i = jax.lax.broadcasted_iota(jnp.int32, (n, n), 0)
    j = jax.lax.broadcasted_iota(jnp.int32, (n, n), 1)
    return j < i


def _strictly_upper(n: int) -> jax.Array:
    """float32 (n, n) with 1 above the diagonal: x @ it = exclusive prefix sums of x."""
    return _before(n).T.astype(jnp.float32)


def _count_by_matmul(x: jax.Array) -> jax.Array:
    xf = x.astype(jnp.float32)
    # Exact in float32: at most MATMUL_PREFIX_MAX ones per sum.
    return jnp.dot(xf, _strictly_upper(x.shape[-1]),
                   precision=jax.lax.Precision.HIGHEST).astype(jnp.int32)


#: Block width of ``_count_by_blocks``.
_COUNT_BLOCK = 16


def _count_by_blocks(x: jax.Array) -> jax.Array:
    """Exclusive prefix counts along the last axis without a matrix product or a scan: within
    blocks of ``_COUNT_BLOCK`` by a masked sum over a (block x block) triangle, plus the
    counts of the blocks before, the same way over the block totals (two small fused
    reductions: cheap to compile into a loop kernel, unlike an associative scan's ladder of
    slices)."""
    n = x.shape[-1]
    b = _COUNT_BLOCK
    m = -(-n // b)
    xi = jnp.pad(x.astype(jnp.int32), [(0, 0)] * (x.ndim - 1) + [(0, m * b - n)])
    xb = xi.reshape(x.shape[:-1] + (m, b))
    tri_b = _before(b)                                                 # (i, j): j before i
    within = jnp.sum(jnp.where(tri_b, xb[..., None, :], 0), axis=-1)   # (..., m, b)
    tri_m = _before(m)
    totals = jnp.sum(xb, axis=-1)                                       # (..., m)
    before = jnp.sum(jnp.where(tri_m, totals[..., None, :], 0), axis=-1)
    out = within + before[..., None]
    return out.reshape(x.shape[:-1] + (m * b,))[..., :n]


def _members(x: jax.Array) -> int:
    """Vectors in x (..., n): the product of its leading axes."""
    return int(np.prod(x.shape[:-1], dtype=np.int64))


def _broadcast_members(axis_size: int, batched: bool, x: jax.Array) -> jax.Array:
    return x if batched else jnp.broadcast_to(x, (axis_size,) + x.shape)


@functools.lru_cache(maxsize=None)
def _exclusive_count_fn():
    @custom_vmap
    def count(x):
        # x (..., n): leading axes are vmapped members (the batching rule folds every vmap
        # level into them, so the choice sees the whole batch of nested vmaps, e.g. seeds x
        # queries).
        wide = x.shape[-1] > MATMUL_PREFIX_MAX
        if wide or (x.ndim > 1 and _members(x) < BIG_BATCH and loop_kernels_enabled()):
            return _count_by_blocks(x)
        return _count_by_matmul(x)    # one vector (a vector-matrix product) or a big batch

    @count.def_vmap
    def count_vmap(axis_size, in_batched, x):
        return count(_broadcast_members(axis_size, in_batched[0], x)), True

    return count


def exclusive_count(x: jax.Array) -> jax.Array:
    """x bool (n,) -> int32 (n,): how many entries before each position are True."""
    if x.ndim != 1:
        raise ValueError(f"exclusive_count expects a vector, got shape {x.shape}")
    return _exclusive_count_fn()(x)


def nth_true(inclusive: jax.Array, r: jax.Array) -> jax.Array:
    """Position of the (r + 1)-th True entry, from the inclusive counts (n,) of a bool
    vector: the number of positions whose count is <= r (a branch-free binary search).
    r int32 (m,) -> int32 (m,); n where fewer than r + 1 entries are True."""
    n = inclusive.shape[-1]
    src = jnp.zeros(r.shape, jnp.int32)
    step = 1 << (n.bit_length() - 1)
    while step:
        cand = jnp.minimum(src + step, n)
        src = jnp.where(inclusive[cand - 1] <= r, cand, src)
        step >>= 1
    return src


def _smallest_k_by_count(values: jax.Array, payload: jax.Array, k: int):
    """``smallest_k`` for one vector without sort or custom call (see the module doc)."""
    n = values.shape[-1]
    bits = jax.lax.bitcast_convert_type(values.astype(jnp.float32), jnp.int32)
    # Non-negative floats order as their bits; -0.0 (sign bit set) is 0, NaN counts as +inf.
    bits = jnp.where(bits < 0, 0, jnp.minimum(bits, _INF_BITS))

    # A cut key t with (#keys < t) <= k <= (#keys <= t), by halving [lo, hi], which always
    # holds the k-th smallest key: a key with exactly k keys at or below it ends the search
    # early (usually after ~15 of the 31 halvings: the k-th and (k+1)-th smallest keys of
    # continuous values are far apart in bits). A loop of unknown trip count, which the
    # compiler does not unroll (unrolled, the kernels took several times longer to compile).
    def halve(lohi):
        lo, hi = lohi
        mid = lo + (hi - lo) // 2
        count = jnp.sum((bits <= mid).astype(jnp.int32))
        enough = count >= k
        return jnp.where(count == k, mid, jnp.where(enough, lo, mid + 1)), \
            jnp.where(enough, mid, hi)

    _, kth = jax.lax.while_loop(lambda lh: lh[0] < lh[1], halve,
                                (jnp.int32(0), jnp.int32(_INF_BITS)))
    below = bits < kth
    tie = bits == kth
    need = k - jnp.sum(below.astype(jnp.int32))
    keep = below | (tie & (exclusive_count(tie) < need))         # exactly k entries
    keep_i = keep.astype(jnp.int32)
    src = nth_true(exclusive_count(keep) + keep_i, jnp.arange(k, dtype=jnp.int32))
    src = jnp.minimum(src, n - 1)
    return values[src], payload[src]


def _smallest_k_by_top_k(values: jax.Array, payload: jax.Array, k: int):
    neg, which = jax.lax.top_k(-values, k)
    return -neg, jnp.take_along_axis(payload, which, axis=-1)


@functools.lru_cache(maxsize=None)
def _smallest_k_fn(k: int):
    @custom_vmap
    def smallest(values, payload):
        # values, payload (..., n): leading axes are vmapped members, as in _exclusive_count.
        if not loop_kernels_enabled() or (values.ndim > 1 and _members(values) >= BIG_BATCH):
            return _smallest_k_by_top_k(values, payload, k)
        one = functools.partial(_smallest_k_by_count, k=k)
        for _ in range(values.ndim - 1):
            one = jax.vmap(one)
        return one(values, payload)

    @smallest.def_vmap
    def smallest_vmap(axis_size, in_batched, values, payload):
        values = _broadcast_members(axis_size, in_batched[0], values)
        payload = _broadcast_members(axis_size, in_batched[1], payload)
        return smallest(values, payload), (True, True)

    return smallest


def smallest_k(values: jax.Array, payload: jax.Array, k: int, kernel_form: bool = True):
    """The k smallest of values float32 (n,) (+0.0 or more, or +inf: e.g. squared distances,
    which are never -0.0 or NaN, whose order here is unspecified; k <= n) with their payload (n,) -> (values (k,), payload (k,)).

    The same entries as ``lax.top_k(-values, k)`` (ties at the k-th value broken by lower
    position). Order: ascending (``top_k``) in vmapped batches of at least ``BIG_BATCH``,
    else by position; callers must not depend on it. ``kernel_form=False``: always
    ``lax.top_k`` (where a loop kernel would not pay: see ``hedger_jax.runtime``).
    """
    if values.ndim != 1 or payload.shape != values.shape:
        raise ValueError(f"smallest_k expects two vectors of one length, got shapes "
                         f"{values.shape} and {payload.shape}")
    k = int(k)
    if not 0 < k <= values.shape[0]:
        raise ValueError(f"smallest_k needs 0 < k <= {values.shape[0]}, got k={k}")
    if not kernel_form:
        return _smallest_k_by_top_k(values, payload, k)
    return _smallest_k_fn(k)(values, payload)
