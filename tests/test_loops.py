"""hedger_jax.loops: a masked loop and a branch that stay cheap under vmap, with the semantics
of a plain fori_loop / lax.cond per member (checked against them, unbatched and under nested
vmaps, with batched and unbatched operands and closed-over values)."""
import jax
import jax.numpy as jnp
import numpy as np

from hedger_jax.loops import batch_cond, masked_fori_loop

TABLE = jnp.arange(7.0) ** 2


def _sum_loop(n, c0, scale):
    """sum_{i < n} scale * TABLE[i % 7] + c0 via the masked loop (the body masks itself)."""
    def body(i, c, active):
        return jnp.where(active, c + scale * TABLE[i % 7], c)

    return masked_fori_loop(n, body, c0)


@jax.jit
def _sum_ref(n, c0, scale):
    """The plain fori_loop (jitted once: called member by member as the reference)."""
    return jax.lax.fori_loop(0, n, lambda i, c: c + scale * TABLE[i % 7], c0)


def test_masked_fori_loop_matches_fori_loop_unbatched_and_jitted():
    for n in (0, 1, 5, 13):
        want = float(_sum_ref(n, 1.0, 2.0))
        assert float(_sum_loop(n, 1.0, 2.0)) == want
        assert float(jax.jit(_sum_loop)(n, 1.0, 2.0)) == want


def test_masked_fori_loop_under_vmap_each_member_its_own_trip_count():
    n = jnp.array([0, 3, 1, 9, 4])
    c0 = jnp.array([0.0, 1.0, -1.0, 2.0, 5.0])
    scale = jnp.array([1.0, 2.0, 3.0, 0.5, -1.0])
    want = np.array([_sum_ref(int(a), float(b), float(c)) for a, b, c in zip(n, c0, scale)])
    np.testing.assert_array_equal(jax.jit(jax.vmap(_sum_loop))(n, c0, scale), want)
    # Unbatched trip count, batched carry; batched count, unbatched carry and closure.
    np.testing.assert_array_equal(jax.vmap(_sum_loop, (None, 0, None))(4, c0, 2.0),
                                  [float(_sum_ref(4, float(b), 2.0)) for b in c0])
    np.testing.assert_array_equal(jax.vmap(_sum_loop, (0, None, None))(n, 1.0, 2.0),
                                  [float(_sum_ref(int(a), 1.0, 2.0)) for a in n])


def test_masked_fori_loop_nested_vmap():
    n = jnp.array([[0, 2, 5], [7, 1, 3]])
    c0 = jnp.arange(6.0).reshape(2, 3)
    scale = jnp.array([1.0, -2.0])
    got = jax.jit(jax.vmap(jax.vmap(_sum_loop, (0, 0, None)), (0, 0, 0)))(n, c0, scale)
    want = [[float(_sum_ref(int(n[i, j]), float(c0[i, j]), float(scale[i])))
             for j in range(3)] for i in range(2)]
    np.testing.assert_array_equal(got, want)


def test_masked_fori_loop_does_not_select_over_a_large_carry_under_vmap():
    """The point of the loop: no O(carry) select per trip (what vmap of fori_loop does)."""
    big = jnp.zeros((4, 50_000))

    def run(n, mem):
        def body(i, m, active):
            return m.at[i].add(jnp.where(active, 1.0, 0.0))
        return masked_fori_loop(n, body, mem)

    hlo = jax.jit(jax.vmap(run)).lower(jnp.array([1, 2, 3, 4]), big).compile().as_text()
    assert "f32[4,50000]{1,0} select(" not in hlo
    out = jax.jit(jax.vmap(run))(jnp.array([1, 2, 3, 4]), big)
    np.testing.assert_array_equal(out.sum(1), [1, 2, 3, 4])


def _branch(p, x, y):
    return batch_cond(p, lambda v: v * y + TABLE[:3], lambda v: v - y, x)


@jax.jit
def _branch_ref(p, x, y):
    """The plain lax.cond (jitted once: called member by member as the reference)."""
    return jax.lax.cond(p, lambda v: v * y + TABLE[:3], lambda v: v - y, x)


def test_batch_cond_matches_lax_cond():
    x = jnp.array([1.0, 2.0, 3.0])
    for p in (True, False):
        np.testing.assert_array_equal(_branch(p, x, 2.0), _branch_ref(p, x, 2.0))
        np.testing.assert_array_equal(jax.jit(_branch)(p, x, 2.0), _branch_ref(p, x, 2.0))
    ps = jnp.array([True, False, True, False])
    xs = jnp.arange(12.0).reshape(4, 3)
    ys = jnp.array([1.0, 2.0, 3.0, 4.0])
    want = np.stack([_branch_ref(bool(p), x, y) for p, x, y in zip(ps, xs, ys)])
    np.testing.assert_array_equal(jax.jit(jax.vmap(_branch))(ps, xs, ys), want)
    none = jnp.zeros(4, bool)
    np.testing.assert_array_equal(jax.vmap(_branch)(none, xs, ys), xs - ys[:, None])
    # Batched predicate over an unbatched operand; nested vmap.
    np.testing.assert_array_equal(jax.vmap(_branch, (0, None, None))(ps, xs[0], 2.0),
                                  [_branch_ref(bool(p), xs[0], 2.0) for p in ps])
    nested = jax.vmap(jax.vmap(_branch, (0, 0, None)), (0, 0, 0))(
        ps.reshape(2, 2), xs.reshape(2, 2, 3), ys[:2])
    np.testing.assert_array_equal(nested.reshape(4, 3), np.stack(
        [_branch_ref(bool(ps[i]), xs[i], ys[i // 2]) for i in range(4)]))


def test_batch_cond_runs_the_true_branch_only_when_some_member_needs_it():
    counter = {"n": 0}

    def counting(v):                      # the "expensive" branch, counted on the host
        def cb(a):
            counter["n"] += 1
            return np.asarray(a) + 100.0
        return jax.pure_callback(cb, jax.ShapeDtypeStruct(v.shape, v.dtype), v,
                                 vmap_method="expand_dims")

    g = jax.jit(jax.vmap(lambda p, x: batch_cond(p, counting, lambda v: v, x)))
    xs = jnp.arange(3.0)
    np.testing.assert_array_equal(g(jnp.zeros(3, bool), xs), xs)
    assert counter["n"] == 0
    np.testing.assert_array_equal(g(jnp.array([False, True, False]), xs), [0.0, 101.0, 2.0])
    assert counter["n"] == 1


def _branch_compact(p, x, y):
    return batch_cond(p, lambda v: v * y + TABLE[:3], lambda v: v - y, x, compact=4)


def _dyadic(rng, size):
    """float32 multiples of 1/8 in [-4, 4): x * y + TABLE is exact in float32, so a fused
    multiply-add (which XLA's CPU code may use in one program and not in another, e.g. on
    AVX-512 machines) rounds the same as a multiply then an add."""
    return (rng.integers(-32, 32, size=size) / 8.0).astype(np.float32)


def test_batch_cond_compact_matches_lax_cond_per_member():
    """compact=G: the members that need the true branch run it G at a time; every member's
    result is still lax.cond's (batch sizes not a multiple of G, none / one / all true,
    batched and unbatched closed-over values, nested vmap)."""
    rng = np.random.default_rng(0)
    f = jax.jit(jax.vmap(_branch_compact))
    for n, n_true in ((11, 0), (11, 1), (11, 5), (11, 11), (3, 2), (4, 4)):
        ps = np.zeros(n, bool)
        ps[rng.choice(n, n_true, replace=False)] = True
        xs = _dyadic(rng, (n, 3))
        ys = _dyadic(rng, n)
        want = np.stack([_branch_ref(bool(p), x, y) for p, x, y in zip(ps, xs, ys)])
        np.testing.assert_array_equal(f(jnp.asarray(ps), jnp.asarray(xs), jnp.asarray(ys)), want)
        # unbatched operand and closed-over y
        got = jax.vmap(_branch_compact, (0, None, None))(jnp.asarray(ps), jnp.asarray(xs[0]), 2.0)
        np.testing.assert_array_equal(got, [_branch_ref(bool(p), xs[0], 2.0) for p in ps])
    ps = jnp.asarray(rng.uniform(size=(3, 9)) < 0.3)
    xs = jnp.asarray(_dyadic(rng, (3, 9, 3)))
    ys = jnp.asarray(_dyadic(rng, 3))
    nested = jax.jit(jax.vmap(jax.vmap(_branch_compact, (0, 0, None))))(ps, xs, ys)
    want = np.stack([[_branch_ref(bool(ps[i, j]), xs[i, j], ys[i]) for j in range(9)]
                     for i in range(3)])
    np.testing.assert_array_equal(nested, want)


def test_batch_cond_compact_runs_the_branch_for_the_needing_members_only():
    seen = []

    def counting(v):                      # records how many members each call carries
        def cb(a):
            seen.append(np.asarray(a).shape[0])
            return np.asarray(a) + 100.0
        return jax.pure_callback(cb, jax.ShapeDtypeStruct(v.shape, v.dtype), v,
                                 vmap_method="expand_dims")

    g = jax.jit(jax.vmap(lambda p, x: batch_cond(p, counting, lambda v: v, x, compact=4)))
    xs = jnp.arange(10.0)
    np.testing.assert_array_equal(g(jnp.zeros(10, bool), xs), xs)
    assert seen == []
    p = np.zeros(10, bool)
    p[[2, 7]] = True
    np.testing.assert_array_equal(g(jnp.asarray(p), xs), np.where(p, xs + 100.0, xs))
    assert seen == [4]                    # one group of 4 (2 members + padding), not 10
    seen.clear()
    p[[0, 1, 3, 9]] = True                # 6 members: two groups
    np.testing.assert_array_equal(g(jnp.asarray(p), xs), np.where(p, xs + 100.0, xs))
    assert seen == [4, 4]


def test_batch_cond_compact_small_batches_run_in_groups_of_four():
    """A batch no larger than G (e.g. 11 candidate actions, G = 16) runs the needing members
    in groups of min(G, 4); a batch of at most 4 runs whole (one call for every member)."""
    seen = []

    def counting(v):
        def cb(a):
            seen.append(np.asarray(a).shape[0])
            return np.asarray(a) + 100.0
        return jax.pure_callback(cb, jax.ShapeDtypeStruct(v.shape, v.dtype), v,
                                 vmap_method="expand_dims")

    g = jax.jit(jax.vmap(lambda p, x: batch_cond(p, counting, lambda v: v, x, compact=16)))
    for n, members, calls in ((11, [], []), (11, [3], [4]), (11, [0, 5, 9, 10, 2], [4, 4]),
                              (4, [1], [4]), (3, [0, 2], [3]), (3, [], [])):
        seen.clear()
        p = np.zeros(n, bool)
        p[members] = True
        xs = jnp.arange(float(n))
        np.testing.assert_array_equal(g(jnp.asarray(p), xs), np.where(p, xs + 100.0, xs))
        assert seen == calls, (n, members, seen)
