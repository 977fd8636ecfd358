"""The k smallest entries of a vector, and the positions of a mask's True entries, in forms
that XLA's CPU backend can compile -- with the loop around them -- into one kernel.

Why. XLA's CPU runtime runs a program as a sequence of small compiled kernels ("thunks"),
paying ~20-100 ns per kernel call; a HEDGER training step is hundreds of tiny kernels, so
that overhead is most of its cost. XLA can instead compile a whole ``while`` loop into a
single kernel (its "small while loop hoisting", enabled for loops of any size by a flag
that ``hedger_jax.runtime`` adds by default on the CPU; ``HEDGER_JAX_LOOP_KERNELS=0`` leaves it
out), but only a loop that contains no custom call, no sort and no batched matrix product.
``lax.top_k`` is a custom call on the CPU. So, with the flag:

* ``smallest_k`` finds the k-th smallest value by a search over the float bits (counting
  passes, one reduction each, cutting at value midpoints first, then halving the bits; in
  a loop the compiler does not unroll), then
  keeps the entries below it and the first ties, compacted in position order: the same set
  as ``lax.top_k`` of the negated values (ties broken by lower position), not sorted. Single
  vectors and vmapped batches of any size (in big batches, which are not one kernel anyway,
  it is faster than ``top_k`` too since the compaction below); from ``MAP_MEMBERS``
  members on, the members are searched one after another.
* ``true_positions`` compacts a mask (the entries kept, a scan trip's accepted candidates)
  through its bits packed into 32-bit words and their population counts, without a prefix
  count over the whole vector.

Without the flag (and with ``smallest_k(kernel_form=False)``), ``lax.top_k`` is used.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap


#: From this many vmapped members on, ``smallest_k`` runs them one after another
#: (``lax.map``) instead of as one batched search (see ``_smallest_k_fn``).
MAP_MEMBERS = 64

#: ``smallest_k``'s search takes this many steps at the midpoint of its range's *values*
#: before it halves the range's float bits (see ``_smallest_k_by_count``).
_VALUE_STEPS = 16

#: Bits of +inf in float32: the largest key of a non-negative value (NaN counts as +inf).
_INF_BITS = 0x7F800000


def cpu_kernels() -> bool:
    """Whether the program is for the CPU, where the loops' sort-free forms pay (the
    backend platform, not the process's flags, decides: a traced function depends only on
    its arguments and the platform)."""
    return jax.default_backend() == "cpu"


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


def _broadcast_members(axis_size: int, batched: bool, x: jax.Array) -> jax.Array:
    return x if batched else jnp.broadcast_to(x, (axis_size,) + x.shape)


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


def true_positions(x: jax.Array, r: jax.Array) -> jax.Array:
    """Position of the (r + 1)-th True entry of x bool (n,) for each r int32 (m,) -> int32
    (m,); n where fewer than r + 1 entries are True (``nth_true`` without the prefix count).

    x is packed into 32-bit words: a word's set bits are counted (population count), the
    word holding the (r + 1)-th True is found by a binary search over the words' running
    totals (a few words: one small masked sum), and the bit inside it by a binary search on
    the counts of its low bits. All elementwise or tiny: no (n,)-long prefix count."""
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
    """``smallest_k`` for one vector without sort or custom call (see the module doc)."""
    n = values.shape[-1]
    bits = jax.lax.bitcast_convert_type(values.astype(jnp.float32), jnp.int32)
    # Non-negative floats order as their bits; -0.0 (sign bit set) is 0, NaN counts as +inf.
    bits = jnp.where(bits < 0, 0, jnp.minimum(bits, _INF_BITS))

    # A cut key t with (#keys < t) <= k <= (#keys <= t), by narrowing [lo, hi], which always
    # holds the k-th smallest key: a key with exactly k keys at or below it ends the search
    # early. The range starts at [0, largest finite key] when at least k keys are finite
    # (else the cut is +inf), and the first ``_VALUE_STEPS`` steps cut it at the midpoint of
    # its values, not of its bits: distances are spread evenly in value, so the k-th and
    # (k+1)-th smallest separate after ~6 such steps instead of ~12 bit halvings (4096 rows
    # of 192 candidates, 60-150 finite: mean 6.6 vs 12.4 steps; 1.11x for the selection).
    # Every step keeps mid in [lo, hi - 1], so the range shrinks; values spread over many
    # magnitudes fall back to bit halvings (at most _VALUE_STEPS + 31 steps). The same cut
    # set, so the same entries: paired, bit-identical, 2-core CPU: training 1.02x discrete /
    # continuous at 3e5 slots, batched predictions 1.01x. A loop of unknown trip count,
    # which the compiler does not unroll (unrolled, the kernels took several times longer
    # to compile).
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
    # Exactly k entries: those below the cut and the first `need` ties, compacted by
    # ``true_positions`` (two prefix counts and a binary search over them cost 4.3x as much:
    # 3.4 vs 0.8 us for 320 values; training paired 1.30x continuous / 1.18x discrete at 3e5
    # slots, 1.11x discrete at 1e6, 1.22x continuous at 1e5, bit-identical; 2-core CPU).
    cut = true_positions(tie, (need - 1)[None])[0]          # the last tie kept (n: all)
    keep = below | (tie & (jnp.arange(n, dtype=jnp.int32) <= cut) & (need > 0))
    src = jnp.minimum(true_positions(keep, jnp.arange(k, dtype=jnp.int32)), n - 1)
    return values[src], payload[src]


def _smallest_k_by_top_k(values: jax.Array, payload: jax.Array, k: int):
    neg, which = jax.lax.top_k(-values, k)
    return -neg, jnp.take_along_axis(payload, which, axis=-1)


@functools.lru_cache(maxsize=None)
def _smallest_k_fn(k: int):
    @custom_vmap
    def smallest(values, payload):
        # values, payload (..., n): leading axes are vmapped members (the batching rule folds
        # every vmap level into them). Big batches too: since the packed compaction the
        # sort-free form beat top_k there as well (batched selection at 3e5 / 1e6 slots
        # 1.27x / 1.17x, predictions 1.05-1.20x discrete, 1.00x continuous; paired,
        # bit-identical, 2-core CPU).
        if not cpu_kernels():
            return _smallest_k_by_top_k(values, payload, k)
        one = functools.partial(_smallest_k_by_count, k=k)
        n = values.shape[-1]
        if values.ndim > 1 and values.size // n >= MAP_MEMBERS:
            # Many members: one after another (a loop kernel: each member's search runs its
            # own halvings on a row in cache), not one batched search, whose every halving
            # passes over all members' rows (~5 MB for 4096 x 320) as often as its slowest
            # member needs (~25 times, against a mean of ~12). Paired, bit-identical,
            # 2-core CPU: batched predictions 1.15x / 1.38x at 3e5 / 1e5 slots (discrete),
            # selection 1.27x continuous at 3e5, 1.08x at 1e6; 16 vmapped training seeds
            # 1.13x, 64 1.02x; from 16 members (0.94x) it pays at 64 (1.00-1.06x).
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
    """The k smallest of values float32 (n,) (+0.0 or more, or +inf: e.g. squared distances,
    which are never -0.0 or NaN, whose order here is unspecified; k <= n) with their payload (n,) -> (values (k,), payload (k,)).

    The same entries as ``lax.top_k(-values, k)`` (ties at the k-th value broken by lower
    position). Order: by position, or ascending where ``top_k`` is used; callers must not
    depend on it. ``kernel_form=False``: always
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
