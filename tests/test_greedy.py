"""Greedy action search: discrete argmax, random action when nothing is known, the 1-D
parabolic-interpolation search (maximise_1d) and the continuous greedy action."""
import functools
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from hedger_jax import (HedgerConfig, add_points, greedy_action, greedy_value,  # noqa: E402
                        init_memory, predict)
from hedger_jax.greedy import maximise_1d  # noqa: E402
from hedger_np_ref import default_k_thresh, f32, ref_predict  # noqa: E402

N_KEYS = 24
KEYS = jax.random.split(jax.random.PRNGKey(0), N_KEYS)
KEYS8 = KEYS[:8]  # the one batch size used for the continuous search (one compilation)

# ------------------------------------------------------------------ discrete
ACTS = ((-1.0,), (0.0,), (1.0,))
CFG_D = HedgerConfig(2, 1, capacity=128, bandwidth=0.1, max_neighbours=16, discrete_actions=ACTS,
                     default_value=0.0)
_greedy_d = jax.jit(jax.vmap(functools.partial(greedy_action, CFG_D), in_axes=(None, None, 0)))
_gvalue_d = jax.jit(functools.partial(greedy_value, CFG_D))
# The discrete predictions of all ACTS at one state.
_each_d = jax.jit(jax.vmap(functools.partial(predict, CFG_D), in_axes=(None, None, 0)))


def _ref(cfg, Z, V, zq):
    return ref_predict(Z, V, len(Z), zq, bandwidth=cfg.bandwidth,
                       k_thresh=default_k_thresh(cfg.bandwidth, cfg.min_weight),
                       k_min=cfg.k_min, max_neighbours=cfg.max_neighbours,
                       default_value=cfg.default_value, use_ivh=cfg.use_ivh,
                       ivh_tol=cfg.ivh_tol)


def _discrete_memory(values_per_action, seed=0, n_per=40, which=(0, 1, 2)):
    """States uniform in [0.4, 0.6]^2; actions exactly the discrete values (a degenerate
    action column in every neighbourhood, as with mountain car's raw {-1, 0, 1})."""
    rng = np.random.default_rng(seed)
    S, A, V = [], [], []
    for i in which:
        s = f32(rng.uniform(0.4, 0.6, (n_per, 2)))
        S.append(s)
        A.append(f32(np.full((n_per, 1), ACTS[i][0])))
        V.append(f32(values_per_action[i](s.astype(np.float64))))
    S, A, V = np.concatenate(S), np.concatenate(A), np.concatenate(V)
    return S, A, V, add_points(CFG_D, init_memory(CFG_D), S, A, V)


def test_discrete_argmax_picks_clearly_best_action():
    fns = (lambda s: 0.2 + 0 * s[:, 0], lambda s: 0.5 + 0.05 * s[:, 1],
           lambda s: 1.0 + 0.1 * s[:, 0])
    S, A, V, mem = _discrete_memory(fns)
    s = f32([0.5, 0.48])
    acts, vals, known = _greedy_d(mem, jnp.asarray(s), KEYS)
    np.testing.assert_array_equal(np.asarray(acts), np.ones((N_KEYS, 1), np.float32))
    assert np.all(np.asarray(known))
    Z = np.concatenate([S, A], 1).astype(np.float64)
    refs = [_ref(CFG_D, Z, V, np.concatenate([s, a]).astype(np.float64)) for a in ACTS]
    assert all(r.known and not r.ambiguous for r in refs)
    np.testing.assert_allclose([r.value for r in refs], [0.2, 0.5 + 0.05 * 0.48, 1.05],
                               rtol=1e-6)
    np.testing.assert_allclose(np.asarray(vals), refs[2].value, rtol=1e-4)
    gv, gk = _gvalue_d(mem, jnp.asarray(s))
    assert bool(gk)
    assert float(gv) == pytest.approx(refs[2].value, rel=1e-4)
    # each candidate's prediction, through predict, matches the reference (degenerate column)
    v, k, n = _each_d(mem, jnp.asarray(s), jnp.asarray(f32(ACTS)))
    for i, r in enumerate(refs):
        assert bool(k[i]) and int(n[i]) == r.n
        assert float(v[i]) == pytest.approx(r.value, rel=1e-4)


def test_discrete_argmax_middle_action():
    fns = (lambda s: 0.3 - s[:, 0], lambda s: 0.9 + 0 * s[:, 0], lambda s: 0.1 + s[:, 1])
    S, A, V, mem = _discrete_memory(fns, seed=1)
    acts, vals, known = _greedy_d(mem, jnp.asarray(f32([0.45, 0.55])), KEYS)
    np.testing.assert_array_equal(np.asarray(acts), np.zeros((N_KEYS, 1), np.float32))
    np.testing.assert_allclose(np.asarray(vals), 0.9, rtol=1e-4)


def test_all_unknown_discrete_is_random_and_unknown():
    mem = init_memory(CFG_D)
    acts, vals, known = _greedy_d(mem, jnp.asarray(f32([0.5, 0.5])), KEYS)
    acts = np.asarray(acts)[:, 0]
    assert not np.any(np.asarray(known))
    assert set(acts.tolist()) <= {-1.0, 0.0, 1.0}
    assert len(set(acts.tolist())) == 3  # 24 uniform draws over 3 actions
    gv, gk = _gvalue_d(mem, jnp.asarray(f32([0.5, 0.5])))
    assert not bool(gk) and float(gv) == CFG_D.default_value


def test_unknown_candidates_count_as_default_value():
    """Only a = +1 is known, with value -1 < default 0: the greedy choice is one of the unknown
    actions (tie at the default, broken at random), never +1."""
    fns = (None, None, lambda s: -1.0 + 0 * s[:, 0])
    S, A, V, mem = _discrete_memory(fns, which=(2,))
    s = jnp.asarray(f32([0.5, 0.5]))
    v, k, _ = _each_d(mem, s, jnp.asarray(f32(ACTS)))
    assert bool(k[2]) and float(v[2]) == pytest.approx(-1.0, rel=1e-5)
    acts, vals, known = _greedy_d(mem, s, KEYS)
    acts = np.asarray(acts)[:, 0]
    assert set(acts.tolist()) == {-1.0, 0.0}
    np.testing.assert_allclose(np.asarray(vals), 0.0, atol=1e-7)
    gv, _ = _gvalue_d(mem, s)
    assert float(gv) == pytest.approx(0.0, abs=1e-7)


def test_greedy_action_key_dependence_only_for_ties():
    fns = (lambda s: 0.2 + 0 * s[:, 0], lambda s: 0.5 + 0 * s[:, 0], lambda s: 1.0 + 0 * s[:, 0])
    _, _, _, mem = _discrete_memory(fns, seed=2)
    acts, _, _ = _greedy_d(mem, jnp.asarray(f32([0.5, 0.5])), KEYS)
    np.testing.assert_array_equal(np.asarray(acts), np.ones((N_KEYS, 1), np.float32))
    one = jax.eval_shape(functools.partial(greedy_action, CFG_D), mem,
                         jnp.asarray(f32([0.5, 0.5])), jax.random.PRNGKey(1))
    assert one[0].shape == (1,) and one[1].shape == () and one[2].shape == ()


# ------------------------------------------------------------------ maximise_1d
def _max1d(f, low, high, n=11, iters=8, tol=1e-3):
    return maximise_1d(f, low, high, n, iters, tol)


@functools.partial(jax.jit, static_argnums=(1, 2))
def _max_cosh(c, low, high):
    return _max1d(lambda x: -jnp.cosh(2.0 * (x - c)), low, high)


@functools.partial(jax.jit, static_argnums=(1, 2))
def _max_skew(c, low, high):
    # smooth, concave, asymmetric: -exp(x - c) - 3 exp(-(x - c)/3) + const, max at x = c
    return _max1d(lambda x: 4.0 - jnp.exp(x - c) - 3.0 * jnp.exp(-(x - c) / 3.0), low, high)


@settings(max_examples=30, deadline=None)
@given(st.floats(-1.5, 1.5, allow_nan=False, width=32))
def test_maximise_1d_finds_maximum_of_smooth_concave_function(c):
    x, fx = _max_cosh(jnp.float32(c), -1.0, 1.0)
    x, fx = float(x), float(fx)
    want = min(max(c, -1.0), 1.0)
    assert -1.0 <= x <= 1.0
    assert abs(x - want) <= 5e-3, (c, x)
    assert fx == pytest.approx(-np.cosh(2.0 * (x - c)), rel=1e-5)
    assert fx >= -np.cosh(2.0 * (want - c)) - 1e-4


@pytest.mark.parametrize("c", [0.37, -0.81, 0.0, 0.999])
def test_maximise_1d_asymmetric_function(c):
    x, fx = _max_skew(jnp.float32(c), -1.0, 1.0)
    assert -1.0 <= float(x) <= 1.0
    assert abs(float(x) - c) <= 5e-3, (c, float(x))


@pytest.mark.parametrize("c, want", [(3.0, 1.0), (-2.5, -1.0), (1.2, 1.0), (1.02, 1.0)])
def test_maximise_1d_maximum_at_a_bound_stays_in_bounds(c, want):
    x, fx = _max_skew(jnp.float32(c), -1.0, 1.0)
    assert -1.0 <= float(x) <= 1.0
    assert float(x) == pytest.approx(want, abs=2e-3)


def test_maximise_1d_other_interval_and_linear():
    x, _ = _max_cosh(jnp.float32(2.7), 2.0, 5.0)
    assert float(x) == pytest.approx(2.7, abs=5e-3)
    x, fx = jax.jit(lambda: _max1d(lambda x: 2.0 * x + 1.0, -0.5, 0.25))()
    assert -0.5 <= float(x) <= 0.25 and float(x) == pytest.approx(0.25, abs=1e-6)
    assert float(fx) == pytest.approx(1.5, rel=1e-6)
    x, _ = _max1d(lambda x: -(x - 0.123) ** 2, -1.0, 1.0)  # unjitted
    assert float(x) == pytest.approx(0.123, abs=1e-3)


def _plain_search(f, low, high, n, iters, tol):
    """The paper's loop as first written: every iteration evaluates the parabola's vertex and
    discards it when it is not a maximum; it stops after a non-concave bracket or two maxima
    closer than tol. -> (x_best, f_best, any_known, number of vertex evaluations)."""
    from hedger_jax.greedy import _bracket, _parabola_vertex, search_grid
    grid = search_grid(low, high, n)
    # The grid evaluated as ``search_1d`` does (one sample after another): XLA may round a
    # vmapped f (here sin, exp) differently in the last bit, and the comparison is bitwise.
    f0, k0 = jax.lax.map(f, grid)
    xs = jnp.zeros((n + iters,), jnp.float32).at[:n].set(grid)
    fs = jnp.full((n + iters,), -jnp.inf, jnp.float32).at[:n].set(f0)
    filled = jnp.arange(n + iters) < n

    def body(c):
        i, xs, fs, filled, prev, done, anyk, evals = c
        p0, p1, p2, _ = _bracket(xs, fs, filled)
        v, concave = _parabola_vertex(p0, p1, p2)
        v = jnp.clip(jnp.clip(v, p0[0], p2[0]), low, high)
        active = ~done & concave
        fv, kv = f(v)
        xs, fs = xs.at[n + i].set(v), fs.at[n + i].set(jnp.where(active, fv, -jnp.inf))
        filled = filled.at[n + i].set(active)
        done = done | ~concave | (jnp.abs(v - prev) < tol)
        return i + 1, xs, fs, filled, v, done, anyk | (active & kv), evals + 1

    init = (0, xs, fs, filled, jnp.float32(jnp.nan), False, jnp.any(k0), 0)
    _, xs, fs, filled, _, _, anyk, evals = jax.lax.while_loop(
        lambda c: (c[0] < iters) & ~c[5], body, init)
    best = jnp.argmax(jnp.where(filled, fs, -jnp.inf))
    return xs[best], fs[best], anyk, evals


def smooth(x, p):
    return -(x - p[0]) ** 2 * (1.0 + p[1]), x > p[2]


def bumpy(x, p):
    return jnp.sin(7.0 * x + 5.0 * p[0]) * jnp.exp(-x * p[1]), jnp.abs(x - p[2]) < 0.5


def flat(x, p):
    return jnp.zeros_like(x), jnp.zeros_like(x, bool)


def steps(x, p):
    return -jnp.abs(jnp.round(4.0 * (x - p[0])) / 4.0), jnp.ones_like(x, bool)


def edge(x, p):
    return 3.0 * p[0] * x - x * x, x < 0.0


#: f(x, params) families: smooth concave, bumpy, flat (all unknown), steps (vertices on
#: samples), maxima at the bounds.
SEARCH_FUNCTIONS = (smooth, bumpy, flat, steps, edge)


def _switched(i, p):
    """SEARCH_FUNCTIONS[i](., p) with i traced (lax.switch): one program serves all five."""
    return lambda x: jax.lax.switch(i, SEARCH_FUNCTIONS, x, p)


@jax.jit
def _search_both(i, params):
    """search_1d and the plain loop on SEARCH_FUNCTIONS[i] for each row of params."""
    from hedger_jax.greedy import search_1d
    ours = jax.vmap(lambda p: search_1d(_switched(i, p), -1.0, 1.0, 11, 8, 1e-3,
                                        with_count=True))(params)
    plain = jax.vmap(lambda p: _plain_search(_switched(i, p), -1.0, 1.0, 11, 8, 1e-3))(params)
    return ours, plain


@pytest.mark.parametrize("i", range(len(SEARCH_FUNCTIONS)),
                         ids=[fn.__name__ for fn in SEARCH_FUNCTIONS])
def test_search_1d_same_answer_as_the_plain_loop_with_fewer_evaluations(i):
    params = jnp.asarray(np.random.default_rng(3).uniform(-1.0, 1.0, (64, 3)), jnp.float32)
    got, want = _search_both(jnp.int32(i), params)
    # Best x and any known bit for bit; its value to rounding: XLA's CPU compiler may contract
    # f's multiply-add (edge: 3 p x - x^2) into an FMA in one program and not in the other.
    for a, b in zip((got[0], got[2]), (want[0], want[2])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_allclose(np.asarray(got[1]), np.asarray(want[1]), rtol=1e-6, atol=1e-7)
    ours, plain = np.asarray(got[3]), np.asarray(want[3])
    assert np.all(ours <= plain) and np.all(ours <= 8)
    # The plain loop's last evaluation is often wasted: a vertex that is not a maximum (flat:
    # 64 -> 0 evaluations) or that repeats a sample (smooth: 128 -> 89, measured).
    assert ours.sum() < plain.sum()


# ------------------------------------------------------------------ continuous greedy
CFG_C = HedgerConfig(1, 1, capacity=256, bandwidth=0.1, max_neighbours=32, action_low=(-1.0,),
                     action_high=(1.0,), greedy_samples=11, greedy_iters=8, greedy_tol=1e-3)
_greedy_c = jax.jit(jax.vmap(functools.partial(greedy_action, CFG_C), in_axes=(None, None, 0)))
_gvalue_c = jax.jit(functools.partial(greedy_value, CFG_C))
_add_c = jax.jit(functools.partial(add_points, CFG_C))
_pred_c = jax.jit(functools.partial(predict, CFG_C))


def _continuous_memory(q_fn, seed=0):
    """A jittered grid: s in {0.42..0.58} (5 rows), a in [-1, 1] step 0.04 (51 columns)."""
    rng = np.random.default_rng(seed)
    ss = np.linspace(0.42, 0.58, 5)
    aa = np.linspace(-1.0, 1.0, 51)
    G = np.array([[s, a] for s in ss for a in aa])
    G[:, 0] += rng.uniform(-0.002, 0.002, len(G))
    G[1:-1, 1] += rng.uniform(-0.002, 0.002, len(G) - 2)
    G[:, 1] = np.clip(G[:, 1], -1.0, 1.0)
    Z = f32(G)
    V = f32(q_fn(Z[:, 0].astype(np.float64), Z[:, 1].astype(np.float64)))
    return Z, V, _add_c(init_memory(CFG_C), Z[:, :1], Z[:, 1:], V)


def test_continuous_greedy_near_argmax_of_quadratic_q():
    Z, V, mem = _continuous_memory(lambda s, a: 1.0 - (a - 0.3) ** 2 + 0.1 * s)
    s0 = f32([0.5])
    acts, vals, known = _greedy_c(mem, jnp.asarray(s0), KEYS8)
    acts, vals = np.asarray(acts)[:, 0], np.asarray(vals)
    assert np.all(np.asarray(known))
    assert np.all((acts >= -1.0) & (acts <= 1.0))
    assert np.all(np.abs(acts - 0.3) <= 0.03), acts
    assert np.all(acts == acts[0])  # deterministic when known
    # value reported = the model's prediction at the returned action
    v, k, _ = _pred_c(mem, jnp.asarray(s0), jnp.asarray(f32([acts[0]])))
    assert bool(k) and float(v) == pytest.approx(float(vals[0]), rel=1e-5)
    # ... which is the reference's prediction there, and close to the reference's max
    grid = np.linspace(-1, 1, 201)
    refs = [_ref(CFG_C, Z, V, np.array([0.5, a])) for a in grid]
    ref_max = max(r.value for r in refs if r.known)
    r_at = _ref(CFG_C, Z, V, np.array([0.5, float(acts[0])]))
    assert r_at.known and float(vals[0]) == pytest.approx(r_at.value, rel=2e-4)
    assert float(vals[0]) >= ref_max - 1e-3
    gv, gk = _gvalue_c(mem, jnp.asarray(s0))
    assert bool(gk) and float(gv) == pytest.approx(float(vals[0]), rel=1e-5)


def test_continuous_greedy_increasing_q_goes_to_upper_bound():
    Z, V, mem = _continuous_memory(lambda s, a: 0.5 + 0.4 * a + 0.1 * s, seed=1)
    acts, vals, known = _greedy_c(mem, jnp.asarray(f32([0.5])), KEYS8)
    a = np.asarray(acts)[:, 0]
    assert np.all(np.asarray(known))
    assert np.all((a <= 1.0) & (a >= 0.97)), a
    np.testing.assert_allclose(np.asarray(vals), 0.5 + 0.4 * a + 0.05, rtol=1e-3)


def test_continuous_greedy_decreasing_q_goes_to_lower_bound():
    Z, V, mem = _continuous_memory(lambda s, a: 0.5 - 0.4 * a ** 3 - 0.2 * a, seed=2)
    acts, vals, known = _greedy_c(mem, jnp.asarray(f32([0.5])), KEYS8)
    a = np.asarray(acts)[:, 0]
    assert np.all(np.asarray(known))
    assert np.all((a >= -1.0) & (a <= -0.97)), a


def test_all_unknown_continuous_is_uniform_random_in_box():
    mem = init_memory(CFG_C)
    acts, vals, known = _greedy_c(mem, jnp.asarray(f32([0.5])), KEYS8)
    a = np.asarray(acts)[:, 0]
    assert not np.any(np.asarray(known))
    assert np.all((a >= -1.0) & (a <= 1.0))
    assert len(np.unique(a)) >= 7
    assert a.min() < -0.2 and a.max() > 0.2  # spread over the box
    gv, gk = _gvalue_c(mem, jnp.asarray(f32([0.5])))
    assert not bool(gk) and float(gv) == CFG_C.default_value


def test_continuous_greedy_state_outside_memory_is_random():
    """Known at s = 0.5, unknown at s = 0.9 (no neighbours there)."""
    Z, V, mem = _continuous_memory(lambda s, a: 1.0 - (a - 0.3) ** 2, seed=3)
    acts, _, known = _greedy_c(mem, jnp.asarray(f32([0.9])), KEYS8)
    assert not np.any(np.asarray(known))
    assert len(np.unique(np.asarray(acts))) >= 7


@pytest.mark.parametrize("continuous", [False, True])
def test_greedy_value_from_a_caller_batch_equals_greedy_value(continuous):
    """train_step evaluates the first candidates of max_a' Q(s', a') in its own batch
    (greedy_candidates + greedy_value_from); the result must be greedy_value's."""
    from hedger_jax.greedy import greedy_candidates, greedy_value_from
    from hedger_jax.memory import scale_inputs
    from hedger_jax.prediction import predict_scaled

    kw = dict(capacity=256, bandwidth=0.15, max_neighbours=16)
    cfg = (HedgerConfig(2, 1, action_low=(-1.0,), action_high=(1.0,), **kw) if continuous
           else HedgerConfig(2, 1, discrete_actions=ACTS, **kw))
    rng = np.random.default_rng(11)
    s = f32(rng.uniform(0, 1, (200, 2)))
    a = f32(rng.uniform(-1, 1, (200, 1))) if continuous else f32(rng.choice([-1, 0, 1], (200, 1)))
    v = f32(np.sin(3 * s[:, 0]) - (a[:, 0] - 0.3 * s[:, 1]) ** 2)      # a smooth maximum in a
    mem = add_points(cfg, init_memory(cfg), s, a, v)
    acts = greedy_candidates(cfg)
    assert acts.shape == ((cfg.greedy_samples, 1) if continuous else (3, 1))

    @jax.jit
    def both(state):
        zs = scale_inputs(cfg, jnp.broadcast_to(state, (acts.shape[0], 2)), acts)
        batch = jax.vmap(lambda z: predict_scaled(cfg, mem, z))(zs)
        return greedy_value_from(cfg, mem, state, batch.value, batch.known), \
            greedy_value(cfg, mem, state)

    known = 0
    for state in f32(rng.uniform(0.1, 0.9, (12, 2))):
        (v1, k1), (v2, k2) = both(jnp.asarray(state))
        assert bool(k1) == bool(k2)
        np.testing.assert_allclose(float(v1), float(v2), rtol=1e-5, atol=1e-6)
        known += bool(k1)
    assert known >= 6                       # the comparison is about learned values


@pytest.mark.parametrize("continuous", [False, True])
def test_explore_action_is_random_with_probability_epsilon_else_greedy(continuous):
    """explore_action (random exploration) skips the greedy search on exploratory steps; its
    action is still, key by key, the random action when the coin u[0] < epsilon and the
    greedy action otherwise, from the same single draw (jitted and vmapped over keys)."""
    from hedger_jax.agent import RunConfig, _random_action_from_uniform, explore_action
    from hedger_jax.greedy import greedy_action_from_uniform, greedy_draws

    kw = dict(capacity=256, bandwidth=0.15, max_neighbours=16)
    cfg = (HedgerConfig(2, 1, action_low=(-1.0,), action_high=(1.0,), **kw) if continuous
           else HedgerConfig(2, 1, discrete_actions=ACTS, **kw))
    run = RunConfig(epsilon=0.3)
    g = np.random.default_rng(3)
    s = f32(g.uniform(0, 1, (150, 2)))
    a = f32(g.uniform(-1, 1, (150, 1))) if continuous else f32(g.choice([-1, 0, 1], (150, 1)))
    mem = add_points(cfg, init_memory(cfg), s, a, f32(np.sin(3 * s[:, 0]) - a[:, 0] ** 2))
    obs = jnp.asarray(f32([0.45, 0.55]))
    n_g = greedy_draws(cfg)

    def reference(key):
        u = jax.random.uniform(key, (1 + n_g + 1,))
        greedy = greedy_action_from_uniform(cfg, mem, obs, u[1:1 + n_g])[0]
        return u[0] < run.epsilon, jnp.where(u[0] < run.epsilon,
                                             _random_action_from_uniform(cfg, u[1 + n_g:]),
                                             greedy)

    keys = jax.random.split(jax.random.PRNGKey(7), 64)
    got, (explored, want) = jax.jit(jax.vmap(
        lambda k: (explore_action(cfg, run, mem, obs, k), reference(k))))(keys)
    # Continuous actions: the same up to float32 rounding. XLA may compile the two
    # computations' arithmetic differently (a multiply-add contracted in one and not the
    # other: 1 ULP), which the search's parabolic step can turn into ~1e-6 of action; a
    # random and a greedy action differ by orders of magnitude more.
    same = (functools.partial(np.testing.assert_allclose, rtol=0, atol=1e-5) if continuous
            else np.testing.assert_array_equal)
    same(np.asarray(got), np.asarray(want))
    one = jax.jit(lambda k: explore_action(cfg, run, mem, obs, k))
    same(np.stack([np.asarray(one(k)) for k in keys[:16]]), np.asarray(want[:16]))
    assert 5 <= int(np.sum(np.asarray(explored))) <= 35        # both branches were taken
    if continuous:                          # the tolerance tells random from greedy apart
        ex, w = np.asarray(explored), np.asarray(want)
        assert np.min(np.abs(w[ex] - w[~ex][0])) > 1e-3


# ------------------------------------------------------------------ integer argmin / argmax
_SPECIAL = np.array([0.0, -0.0, 1.0, -1.0, np.inf, -np.inf, 0.5, 2.5e-39, 3.4e38, -3.4e38],
                    np.float32)


@jax.jit
def _argmax_argmin(x, a):
    """``_argmax_float(x)`` and ``_argmin_nonneg(a)``: one program per length."""
    from hedger_jax.greedy import _argmax_float, _argmin_nonneg
    return _argmax_float(x), _argmin_nonneg(a)


@pytest.mark.parametrize("seed", range(4))
def test_integer_argmax_and_argmin_equal_numpy_with_ties_zeros_and_infinities(seed):
    """``_argmax_float`` / ``_argmin_nonneg`` (the search's bracket) return NumPy's index --
    the first of equal values -- on values drawn from a few special ones (many ties, +-0,
    +-inf, a subnormal) and on random normals, for every length up to the search's 19."""
    rng = np.random.default_rng(seed)
    for n in range(1, 20):
        for x in (rng.choice(_SPECIAL, n), rng.standard_normal(n).astype(np.float32),
                  np.full(n, -np.inf, np.float32)):
            x = x.astype(np.float32)
            a = np.abs(x)
            i_max, i_min = _argmax_argmin(jnp.asarray(x), jnp.asarray(a))
            assert int(i_max) == int(np.argmax(x)), x
            assert int(i_min) == int(np.argmin(a)), a


# ------------------------------------------------------------------ random_ties
def _flat_search(ties):
    from hedger_jax.greedy import search_1d
    return search_1d(lambda x: (jnp.float32(0.25), jnp.ones((), bool)), -1.0, 1.0, 11, 8, 1e-3,
                     ties=ties)


@pytest.mark.parametrize("u", [0.0, 0.3, 0.55, 0.999])
def test_search_1d_random_ties_picks_the_draws_share_of_the_tied_samples(u):
    """A flat function ties all 11 grid samples: with the switch on, the draw u picks sample
    floor(11 u) (closed form); off, the first (-1); the value is the tied value either way."""
    from hedger_jax.greedy import search_grid
    grid = np.asarray(search_grid(-1.0, 1.0, 11))
    x, fx, known = jax.jit(_flat_search)((jnp.bool_(True), jnp.float32(u)))
    assert float(x) == grid[int(np.floor(11 * u))] and float(fx) == 0.25 and bool(known)
    x_off, _, _ = jax.jit(_flat_search)((jnp.bool_(False), jnp.float32(u)))
    assert float(x_off) == -1.0


def test_search_1d_random_ties_leave_a_unique_maximum_alone():
    """With one best grid sample the draw changes nothing. (The maximum is at 0.33, not
    0.3: the grid's 0.2 and 0.4 would tie on paper there, and float rounding, which differs
    between CPUs, would decide whether they tie in float32.)"""
    from hedger_jax.greedy import search_1d, search_grid
    f = lambda x: (1.0 - (x - 0.33) ** 2, jnp.ones((), bool))  # noqa: E731
    grid = np.asarray(search_grid(-1.0, 1.0, 11), np.float64)
    top2 = np.sort(1.0 - (grid - 0.33) ** 2)[-2:]
    assert top2[1] - top2[0] > 0.01                               # one best sample
    want = search_1d(f, -1.0, 1.0, 11, 8, 1e-3)
    for u in (0.0, 0.5, 0.99):
        got = search_1d(f, -1.0, 1.0, 11, 8, 1e-3, ties=(jnp.bool_(True), jnp.float32(u)))
        assert float(got[0]) == float(want[0]) and float(got[1]) == float(want[1]), u
    assert float(want[0]) == pytest.approx(0.33, abs=2e-3)


def _stack(config, *settings):
    """HedgerParams for each dict of settings, stacked on a leading axis."""
    from hedger_jax import HedgerParams
    return jax.tree_util.tree_map(lambda *x: jnp.stack([jnp.asarray(v) for v in x]),
                                  *[HedgerParams.create(config, **kw) for kw in settings])


def _two_settings_program(config):
    """greedy_action for 2 stacked HedgerParams x 64 keys each (keys (2, 64)): ONE program
    per config (traced settings compile ~4x longer than the config's constants), shared by
    the random_ties and guess_unknown tests."""
    one = lambda mem, s, p, k: greedy_action(config, mem, s, k, p)  # noqa: E731
    return jax.jit(jax.vmap(jax.vmap(one, in_axes=(None, None, None, 0)),
                            in_axes=(None, None, 0, 0)))


KEYS64 = jax.random.split(jax.random.PRNGKey(3), 64)
_greedy_cp = _two_settings_program(CFG_C)
_greedy_dp = _two_settings_program(CFG_D)


def _greedy_two(program, config, mem, s, first, second, keys=None):
    """(actions (2, K, A), values (2, K), known (2, K)) under two settings (dicts), with
    keys (2, K) (default KEYS64 for both)."""
    keys = jnp.stack([KEYS64, KEYS64]) if keys is None else keys
    return program(mem, jnp.asarray(s), _stack(config, first, second), keys)


def test_continuous_greedy_random_ties_spread_over_the_grid_and_default_off():
    """Every stored value 0 (as before any reward has been backed up): every sample is known
    with the fit exactly 0, so ties to the first always take the low end; with
    ``random_ties`` the greedy action is uniform over the 11 samples (chi-square, 512 keys),
    still known."""
    from hedger_jax.greedy import search_grid
    Z, V, mem = _continuous_memory(lambda s, a: 0.0 * a, seed=4)
    s0 = jnp.asarray(f32([0.5]))
    acts, vals, known = _greedy_c(mem, s0, KEYS8)
    assert np.all(np.asarray(known)) and np.all(np.asarray(acts) == -1.0)
    on = dict(random_ties=True)
    keys = jax.random.split(jax.random.PRNGKey(7), 512).reshape(4, 2, 64, -1)
    out = [_greedy_two(_greedy_cp, CFG_C, mem, s0, on, on, k) for k in keys]
    a = np.concatenate([np.asarray(o[0]).ravel() for o in out])
    grid = np.asarray(search_grid(-1.0, 1.0, 11))
    assert all(np.all(np.asarray(o[2])) for o in out) and np.all(np.isin(a, grid))
    assert all(np.all(np.asarray(o[1]) == 0.0) for o in out)
    counts = np.array([(a == g).sum() for g in grid])
    chi2 = ((counts - len(a) / 11) ** 2 / (len(a) / 11)).sum()
    assert chi2 < 29.6, counts         # the 0.999 quantile of chi-square with 10 dof


def test_random_ties_is_a_traced_switch():
    """One program, the switch vmapped: False gives ties to the first, True spreads."""
    Z, V, mem = _continuous_memory(lambda s, a: 0.0 * a, seed=4)
    acts = _greedy_two(_greedy_cp, CFG_C, mem, f32([0.5]), dict(random_ties=False),
                       dict(random_ties=True))[0]
    acts = np.asarray(acts)[..., 0]
    assert np.all(acts[0] == -1.0) and len(np.unique(acts[1])) >= 8


# ------------------------------------------------------------------ guess_unknown
OFF, ON = dict(guess_unknown=False), dict(guess_unknown=True)


def test_guess_unknown_continuous_follows_the_fit_without_the_hull_check():
    """s = 0.64 lies beyond the stored rows (0.42 ... 0.58) but within the kernel: every
    candidate has neighbours, none is inside their hull (float64 reference). Off: random
    (the paper). On: the search over the fits without the hull check, which the reference
    puts at a = 0.3; the value stays the default and ``known`` False."""
    q = lambda s, a: 1.0 - (a - 0.3) ** 2 + 0.5 * s  # noqa: E731
    Z, V, mem = _continuous_memory(q, seed=5)
    grid = np.linspace(-1.0, 1.0, 201)
    ivh = [_ref(CFG_C, Z, V, np.array([0.64, a])) for a in grid]
    assert not any(r.known for r in ivh) and min(r.n for r in ivh) >= CFG_C.k_min
    no_ivh = [ref_predict(Z, V, len(Z), np.array([0.64, a]), bandwidth=CFG_C.bandwidth,
                          k_thresh=default_k_thresh(CFG_C.bandwidth, CFG_C.min_weight),
                          k_min=CFG_C.k_min, max_neighbours=CFG_C.max_neighbours,
                          use_ivh=False) for a in grid]
    assert all(r.known for r in no_ivh)
    ref_best = grid[int(np.argmax([r.value for r in no_ivh]))]
    acts, vals, known = _greedy_two(_greedy_cp, CFG_C, mem, f32([0.64]), OFF, ON)
    acts = np.asarray(acts)[..., 0]
    assert not np.any(np.asarray(known)) and np.all(np.asarray(vals) == CFG_C.default_value)
    assert len(np.unique(acts[0])) >= 50                      # off: uniformly random
    assert np.all(acts[1] == acts[1][0]) and abs(acts[1][0] - ref_best) <= 0.02, acts[1]
    r_at = ref_predict(Z, V, len(Z), np.array([0.64, float(acts[1][0])]),
                       bandwidth=CFG_C.bandwidth,
                       k_thresh=default_k_thresh(CFG_C.bandwidth, CFG_C.min_weight),
                       k_min=CFG_C.k_min, max_neighbours=CFG_C.max_neighbours, use_ivh=False)
    assert r_at.value >= max(r.value for r in no_ivh) - 1e-3
    # Where something is known the switch changes nothing.
    known_acts = np.asarray(_greedy_two(_greedy_cp, CFG_C, mem, f32([0.5]), OFF, ON)[0])
    np.testing.assert_array_equal(known_acts[0], known_acts[1])


def test_guess_unknown_discrete_takes_the_best_fit_without_the_hull_check():
    """States beyond the stored square [0.4, 0.6]^2 but within the kernel: no action is
    inside its neighbours' hull; the fits without the check (float64 reference) rank +1
    first. On: +1 for every key; off: all three actions."""
    fns = (lambda s: 0.2 + 0 * s[:, 0], lambda s: 0.5 + 0.05 * s[:, 1],
           lambda s: 1.0 + 0.1 * s[:, 0])
    S, A, V, mem = _discrete_memory(fns, seed=6)
    s = f32([0.66, 0.5])
    Z = np.concatenate([S, A], 1).astype(np.float64)
    zq = [np.concatenate([s, a]).astype(np.float64) for a in ACTS]
    assert not any(_ref(CFG_D, Z, V, z).known for z in zq)
    no_ivh = [ref_predict(Z, V, len(Z), z, bandwidth=CFG_D.bandwidth,
                          k_thresh=default_k_thresh(CFG_D.bandwidth, CFG_D.min_weight),
                          k_min=CFG_D.k_min, max_neighbours=CFG_D.max_neighbours,
                          use_ivh=False) for z in zq]
    assert all(r.known and not r.ambiguous for r in no_ivh)
    values = sorted(r.value for r in no_ivh)
    assert int(np.argmax([r.value for r in no_ivh])) == 2 and values[2] - values[1] > 0.1
    acts, vals, known = _greedy_two(_greedy_dp, CFG_D, mem, s, OFF, ON)
    acts = np.asarray(acts)[..., 0]
    assert not np.any(np.asarray(known)) and np.all(np.asarray(vals) == CFG_D.default_value)
    assert set(acts[0].tolist()) == {-1.0, 0.0, 1.0}
    assert np.all(acts[1] == 1.0)
    # Without neighbours (far from all data) the guess knows nothing either: random.
    far = _greedy_two(_greedy_dp, CFG_D, mem, f32([3.0, 3.0]), OFF, ON)[0]
    assert set(np.asarray(far)[1, :, 0].tolist()) == {-1.0, 0.0, 1.0}
