"""The k smallest entries of a vector, and the positions of a mask's True entries, without
sort or custom call.

Why: on the CPU a HEDGER step is hundreds of tiny kernels whose call overhead dominates, and
XLA can compile a whole ``while`` loop into one kernel (the loop-kernel flag of
``hedger_jax.cpu.configure``) only if the loop holds no custom call, no sort and no batched
matrix product. ``lax.top_k`` is a custom call there; these forms are not.

* ``smallest_k(values, payload, k)``: the same entries as ``lax.top_k(-values, k)`` (ties to
  the lower position), in no promised order. On the CPU the k-th smallest value is found by a
  search over the float bits (counting passes), then the entries below it and the first ties
  are compacted; a vmapped batch of ``MAP_MEMBERS`` or more members is searched member by
  member. On other backends, or with ``kernel_form=False``, it is ``lax.top_k``.
* ``true_positions(x, r)``: positions of the (r + 1)-th True entries of a mask, through its
  bits packed into 32-bit words and their population counts (no prefix count over x).
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap


#: From this many vmapped members on, ``smallest_k`` searches them one after another
#: (``lax.map``), each on its own row in cache, not as one batched search.
MAP_MEMBERS = 64

#: Steps of ``smallest_k``'s search that cut its range at the midpoint of the *values*
#: before it halves the float bits (see ``_smallest_k_by_count``).
_VALUE_STEPS = 16

#: Bits of +inf in float32: the largest key of a non-negative value (NaN counts as +inf).
_INF_BITS = 0x7F800000


def cpu_kernels() -> bool:
    """Whether the program is for the CPU, where the sort-free forms are used. The backend
    platform decides, not the process's XLA flags, so a traced function depends only on its
    arguments and the platform."""
    return jax.default_backend() == "cpu"


def _before(n: int) -> jax.Array:
    """bool (n, n): entry (i, j) is True when j < i.

    Built from iotas, not a NumPy constant: a constant inside a ``custom_vmap`` function
    becomes an operand of the call, which an enclosing ``lax.cond`` with a batched predicate
    broadcasts, and ``custom_vmap`` refuses a batched constant."""
    i = jax.lax.broadcasted_iota(jnp.int32, (n, n), 0)
    j = jax.lax.broadcasted_iota(jnp.int32, (n, n), 1)
    return j < i


def _broadcast_members(axis_size: int, batched: bool, x: jax.Array) -> jax.Array:
    """x with a leading member axis of ``axis_size`` (broadcast unless already batched)."""
    return x if batched else jnp.broadcast_to(x, (axis_size,) + x.shape)


def nth_true(inclusive: jax.Array, r: jax.Array) -> jax.Array:
    """Position of the (r + 1)-th True entry of a bool vector, from its inclusive counts
    int32 (n,): the number of positions whose count is <= r (a branch-free binary search).
    r int32 (m,) -> int32 (m,); n where fewer than r + 1 entries are True."""
    n = inclusive.shape[-1]
    src = jnp.zeros(r.shape, jnp.int32)
    step = 1 << (n.bit_length() - 1)
    while step:
        cand = jnp.minimum(src + step, n)
        src = jnp.where(inclusive[cand - 1] <= r, cand, src)
        step >>= 1
    return src


def true_positions(x: jax.Array, r: jax.Array) -> jax.Array:
    """Position of the (r + 1)-th True entry of x bool (n,) for each r int32 (m,) -> int32
    (m,); n where fewer than r + 1 entries are True (``nth_true`` without the prefix count).

    x is packed into 32-bit words; the word holding the (r + 1)-th True is found by a binary
    search over the words' running totals of population counts, the bit inside it by a
    binary search on the counts of its low bits. All elementwise or tiny: no (n,)-long
    prefix count, so it stays inside a loop kernel."""
    if x.ndim != 1 or x.dtype != jnp.bool_:
        raise ValueError(f"true_positions expects a bool vector, got {x.dtype} {x.shape}")
    n = x.shape[-1]
    nw = -(-n // 32)
    xb = jnp.pad(x, (0, nw * 32 - n)).reshape(nw, 32).astype(jnp.uint32)
    words = jnp.sum(xb << jnp.arange(32, dtype=jnp.uint32), axis=1, dtype=jnp.uint32)
    cnt = jax.lax.population_count(words).astype(jnp.int32)               # (nw,)
    upto = ~_before(nw)                                   # (i, j): word i is at or before j
    incl = jnp.sum(jnp.where(upto, cnt[:, None], 0), axis=0)              # (nw,) inclusive
    w = nth_true(incl, r)                   # words whose running total is <= r: r's word
    wc = jnp.minimum(w, nw - 1)
    rem = r - (incl[wc] - cnt[wc])                                        # rank in the word
    word = words[wc]
    pos = jnp.zeros(r.shape, jnp.int32)
    for step in (16, 8, 4, 2, 1):
        cand = pos + step
        low = word & ((jnp.uint32(1) << cand.astype(jnp.uint32)) - jnp.uint32(1))
        pos = jnp.where(jax.lax.population_count(low).astype(jnp.int32) <= rem, cand, pos)
    return jnp.where(w < nw, jnp.minimum(wc * 32 + pos, n), n)


def _smallest_k_by_count(values: jax.Array, payload: jax.Array, k: int):
    """``smallest_k`` for one vector (n,) without sort or custom call: a search for the cut
    key, then compaction of the entries kept."""
    n = values.shape[-1]
    bits = jax.lax.bitcast_convert_type(values.astype(jnp.float32), jnp.int32)
    # Non-negative floats order as their bits; -0.0 (sign bit set) is 0, NaN counts as +inf.
    bits = jnp.where(bits < 0, 0, jnp.minimum(bits, _INF_BITS))

    # A cut key t with (#keys < t) <= k <= (#keys <= t), by narrowing [lo, hi], which always
    # holds the k-th smallest key; a mid with exactly k keys at or below it ends the search.
    # Starts at [0, largest finite key] when at least k keys are finite, else the cut is +inf.
    # The first _VALUE_STEPS steps cut at the midpoint of the values (distances spread evenly
    # in value separate sooner), then the bits are halved: at most _VALUE_STEPS + 31 steps.
    # mid stays in [lo, hi - 1], so the range always shrinks. A while loop, so it is not
    # unrolled (unrolled kernels compile far slower).
    finite = bits < _INF_BITS
    enough_finite = jnp.sum(finite.astype(jnp.int32)) >= k
    hi0 = jnp.where(enough_finite, jnp.max(jnp.where(finite, bits, 0)), _INF_BITS)
    lo0 = jnp.where(enough_finite, 0, _INF_BITS)

    def halve(c):
        lo, hi, step = c
        flo = jax.lax.bitcast_convert_type(lo, jnp.float32)
        fhi = jax.lax.bitcast_convert_type(hi, jnp.float32)
        vmid = jax.lax.bitcast_convert_type(flo + (fhi - flo) * 0.5, jnp.int32)
        mid = jnp.where(step < _VALUE_STEPS, jnp.clip(vmid, lo, hi - 1), lo + (hi - lo) // 2)
        count = jnp.sum((bits <= mid).astype(jnp.int32))
        enough = count >= k
        return (jnp.where(count == k, mid, jnp.where(enough, lo, mid + 1)),
                jnp.where(enough, mid, hi), step + 1)

    _, kth, _ = jax.lax.while_loop(lambda c: c[0] < c[1], halve,
                                   (lo0, hi0, jnp.int32(0)))
    below = bits < kth
    tie = bits == kth
    need = k - jnp.sum(below.astype(jnp.int32))
    # Exactly k entries: those below the cut and the first `need` ties, in position order.
    cut = true_positions(tie, (need - 1)[None])[0]          # the last tie kept (n: all)
    keep = below | (tie & (jnp.arange(n, dtype=jnp.int32) <= cut) & (need > 0))
    src = jnp.minimum(true_positions(keep, jnp.arange(k, dtype=jnp.int32)), n - 1)
    return values[src], payload[src]


def _smallest_k_by_top_k(values: jax.Array, payload: jax.Array, k: int):
    """``smallest_k`` by ``lax.top_k`` (ascending order); any leading axes."""
    neg, which = jax.lax.top_k(-values, k)
    return -neg, jnp.take_along_axis(payload, which, axis=-1)


@functools.lru_cache(maxsize=None)
def _smallest_k_fn(k: int):
    """The selection of k entries as a ``custom_vmap`` function of (values, payload)."""

    @custom_vmap
    def smallest(values, payload):
        # values, payload (..., n): leading axes are vmapped members (the batching rule folds
        # every vmap level into them).
        if not cpu_kernels():
            return _smallest_k_by_top_k(values, payload, k)
        one = functools.partial(_smallest_k_by_count, k=k)
        n = values.shape[-1]
        if values.ndim > 1 and values.size // n >= MAP_MEMBERS:
            # One member after another: a batched search would pass over every member's row
            # as many times as its slowest member needs.
            out = jax.lax.map(lambda vp: one(*vp), (values.reshape(-1, n),
                                                     payload.reshape(-1, n)))
            return tuple(o.reshape(values.shape[:-1] + (k,)) for o in out)
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
    """The k smallest of values with their payload: values float32 (n,), payload (n,), static
    0 < k <= n -> (values (k,), payload (k,)).

    values must be +0.0 or more, or +inf (e.g. squared distances); where -0.0 or NaN occur
    their order is unspecified. The same entries as ``lax.top_k(-values, k)``, ties at the
    k-th value to the lower position. Order: by position (sort-free form) or ascending
    (``top_k``); callers must not depend on it. Vmappable at any depth.
    ``kernel_form=False``: always ``lax.top_k``, for callers where the sort-free form
    does not pay.
    Raises ``ValueError`` for non-vector inputs or k out of range.
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
