"""Memory-wide backups (``hedger_jax.backup``) against a float64 NumPy sweep written here."""
import functools
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from hedger_jax import HedgerConfig, HedgerParams, add_points, init_memory  # noqa: E402
from hedger_jax.agent import train_prefix  # noqa: E402
from hedger_jax.backup import backup_memory, backup_targets  # noqa: E402
from hedger_jax.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402
from hedger_jax.greedy import greedy_value  # noqa: E402
from hedger_jax.memory import FLAG_NONFINITE, StoredTransitions  # noqa: E402
from hedger_jax.train import Transition, train_episode  # noqa: E402
from hedger_np_ref import RefParams, default_k_thresh, f32, from_fit, to_fit  # noqa: E402

ACTIONS = ((-0.05,), (0.0,), (0.05,))
N = 160


def _config(**kw):
    base = dict(capacity=192, bandwidth=0.1, max_neighbours=16, alpha=0.7, gamma=0.9,
                default_value=0.1, discrete_actions=ACTIONS, action_low=(-0.1,),
                action_high=(0.1,), backup_sweeps=1)
    base.update(kw)
    return HedgerConfig(2, 1, **base)


def _memory(cfg, seed=0, reward_shift=0.0):
    """A memory of N points of a smooth value function, each with a hand-made transition
    (next states inside the data, a few terminal)."""
    rng = np.random.default_rng(seed)
    S = f32(rng.uniform(0.0, 0.3, (N, 2)))
    A = f32(rng.choice(np.asarray(ACTIONS)[:, 0], (N, 1)))
    V = f32(0.3 + S @ np.array([0.5, -0.4]) + 2.0 * A[:, 0] + 0.02 * rng.standard_normal(N))
    mem = add_points(cfg, init_memory(cfg), S, A, V)
    cap = cfg.capacity
    reward = np.zeros(cap, np.float32)
    reward[:N] = f32(rng.normal(size=N) + reward_shift)
    nxt = np.zeros((2, cap), np.float32)
    nxt[:, :N] = f32(rng.uniform(0.03, 0.27, (N, 2))).T
    term = np.zeros(cap, bool)
    term[:N] = rng.uniform(size=N) < 0.15
    present = np.arange(cap) < N
    present[5] = False                      # a point stored without a transition
    stored = StoredTransitions(jnp.asarray(reward), jnp.asarray(nxt), jnp.asarray(term),
                               jnp.asarray(present))
    return mem._replace(transitions=stored)


def _reference_sweep(cfg, mem):
    """float64: y_i = r_i + gamma max_a Q(s'_i, a) (0 at a terminal; the max over known
    predictions, default_value where none is known), Q_i += alpha (y_i - Q_i) for every
    present slot, all from the memory before the sweep. Returns (new values as
    stored (fit space), a mask of the slots whose max was not ambiguous)."""
    refp = RefParams(bandwidth=cfg.bandwidth, k_min=cfg.k_min, max_neighbours=cfg.max_neighbours,
                     k_thresh=default_k_thresh(cfg.bandwidth, cfg.min_weight),
                     default_value=cfg.default_value, ivh_tol=cfg.ivh_tol,
                     value_eps=cfg.value_eps)
    size = int(mem.size)
    P = np.asarray(mem.points, np.float64)[:, :size].T
    V = np.asarray(mem.values, np.float64)[:size]          # as stored (fit space)
    raw = from_fit(V, cfg.value_eps)
    tr = jax.tree_util.tree_map(np.asarray, mem.transitions)
    out, clear = V.copy(), np.ones(size, bool)
    for i in range(size):
        if not tr.present[i]:
            continue
        q_next = -np.inf
        for a in ACTIONS:
            r = refp.predict(P, raw, size, np.concatenate([tr.next_obs[:, i], a]))
            clear[i] &= not r.ambiguous
            q_next = max(q_next, r.value) if r.known else q_next
        q_next = cfg.default_value if q_next == -np.inf else q_next
        y = float(tr.reward[i]) + cfg.gamma * (0.0 if tr.terminated[i] else q_next)
        out[i] = to_fit(raw[i] + cfg.alpha * (y - raw[i]), cfg.value_eps)
    return out, clear


def _assert_sweep(cfg, mem, got):
    want, clear = _reference_sweep(cfg, mem)
    got = np.asarray(got.values, np.float64)[:len(want)]
    assert clear.mean() > 0.8
    scale = max(1.0, np.abs(want).max())
    np.testing.assert_allclose(got[clear], want[clear], rtol=3e-4, atol=3e-4 * scale)
    assert got[5] == np.asarray(mem.values)[5]           # no transition: not backed up


@pytest.mark.parametrize("value_eps", [0.0, 1e-3])
def test_a_sweep_equals_the_float64_reference_under_jit(value_eps):
    cfg = _config(value_eps=value_eps)
    mem = _memory(cfg)
    _assert_sweep(cfg, mem, jax.jit(functools.partial(backup_memory, cfg))(mem))


def test_a_sweep_equals_the_reference_for_each_memory_under_vmap():
    """Two memories (different rewards) and two alphas, vmapped in one program."""
    cfg = _config()
    mems = [_memory(cfg, seed=1), _memory(cfg, seed=2, reward_shift=3.0)]
    batch = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *mems)
    params = jax.tree_util.tree_map(lambda *x: jnp.stack(x), HedgerParams.create(cfg, alpha=0.7),
                                    HedgerParams.create(cfg, alpha=1.0))
    out = jax.jit(jax.vmap(functools.partial(backup_memory, cfg)))(batch, params)
    for b, (m, alpha) in enumerate(zip(mems, (0.7, 1.0))):
        _assert_sweep(_config(alpha=alpha), m, jax.tree_util.tree_map(lambda x: x[b], out))


def _grid_known_max(cfg, mem, states):
    """max over greedy_candidates of the known predictions at each state (default_value where
    none is known), from ``predict`` itself."""
    from hedger_jax.greedy import greedy_candidates
    from hedger_jax.prediction import predict

    acts = greedy_candidates(cfg)
    v, k, _ = jax.jit(jax.vmap(lambda s: jax.vmap(lambda a: predict(cfg, mem, s, a))(acts)))(
        states)
    v, k = np.asarray(v, np.float64), np.asarray(k)
    return np.where(k.any(1), np.where(k, v, -np.inf).max(1), cfg.default_value), k


def test_targets_of_continuous_actions_use_the_search_grid_chunk_by_chunk():
    """Continuous actions: every target is r + gamma (the max of the known predictions over
    the search's initial grid) of its own point, also across chunk boundaries (a capacity
    that is not a multiple of the chunk). A plan's sweep runs over its own rows chunk by
    chunk and gives the same targets: with 64 rows a chunk (3 chunks for 160 points) and
    with 159 (the second chunk moved back to end at the capacity, overlapping the first)."""
    from hedger_jax import backup

    cfg = _config(discrete_actions=None, capacity=300)
    mem = _memory(cfg)
    old = backup.BACKUP_CHUNK
    backup.BACKUP_CHUNK = 64
    try:
        y, use = jax.jit(functools.partial(backup_targets, cfg))(mem)
        plans = {}
        for chunk in (64, 159):
            backup.BACKUP_CHUNK = chunk
            plans[chunk] = jax.jit(lambda m: backup.plan_targets(
                cfg, m, backup.backup_plan(cfg, m)))(mem)
    finally:
        backup.BACKUP_CHUNK = old
    for chunk, (y_plan, use_plan) in plans.items():
        np.testing.assert_array_equal(np.asarray(use_plan), np.asarray(use))
        np.testing.assert_allclose(np.asarray(y_plan)[:N], np.asarray(y)[:N], rtol=1e-6,
                                   atol=1e-6, err_msg=str(chunk))
    tr = jax.tree_util.tree_map(np.asarray, mem.transitions)
    q, _ = _grid_known_max(cfg, mem, tr.next_obs.T[:N])
    want = tr.reward[:N] + cfg.gamma * np.where(tr.terminated[:N], 0.0, q)
    np.testing.assert_allclose(np.asarray(y)[:N], want, rtol=1e-5, atol=1e-5)
    assert np.asarray(use).sum() == N - 1


def test_an_unknown_candidate_does_not_enter_the_max_however_high_its_default():
    """With "don't know" worth 100 (far above every stored value), a next state with some
    candidates known and some not takes the max of the known ones; one with none known takes
    the default. Exact sweep and plan agree, discrete and continuous."""
    from hedger_jax.backup import backup_plan, plan_targets

    # The discrete set gets an action no stored point is near: never known.
    for acts in (ACTIONS + ((1.0,),), None):
        cfg = _config(default_value=100.0, discrete_actions=acts)
        mem = _memory(cfg)
        tr = jax.tree_util.tree_map(np.asarray, mem.transitions)
        # Next states far outside the data for the first 10 points: nothing known there.
        nxt = tr.next_obs.copy()
        nxt[:, :10] = 5.0
        mem = mem._replace(transitions=mem.transitions._replace(next_obs=jnp.asarray(nxt)))
        q, k = _grid_known_max(cfg, mem, nxt.T[:N])
        partly = k.any(1) & ~k.all(1)
        assert partly.sum() >= 3 and not k[:10].any()
        assert np.all(q[partly] < 10.0) and np.all(q[:10] == 100.0)
        want = tr.reward[:N] + cfg.gamma * np.where(tr.terminated[:N], 0.0, q)
        y, _ = jax.jit(functools.partial(backup_targets, cfg))(mem)
        y_plan, _ = jax.jit(lambda m: plan_targets(cfg, m, backup_plan(cfg, m)))(mem)
        for got in (y, y_plan):
            np.testing.assert_allclose(np.asarray(got)[:N], want, rtol=1e-4, atol=1e-4)


def test_the_replay_stores_each_transition_beside_its_point_and_then_sweeps():
    """train_prefix with backup_sweeps=2: the replay's points keep their transitions, and the
    result is the replay followed by two sweeps."""
    cfg = _config(backup_sweeps=2)
    rng = np.random.default_rng(3)
    T = 30
    ep = Transition(f32(rng.uniform(0, 0.3, (T, 2))),
                    f32(rng.choice(np.asarray(ACTIONS)[:, 0], (T, 1))),
                    f32(rng.normal(size=T)), f32(rng.uniform(0, 0.3, (T, 2))),
                    rng.uniform(size=T) < 0.1, np.ones(T, bool))
    mem = _memory(cfg)
    got = jax.jit(functools.partial(train_prefix, cfg))(mem, ep, jnp.int32(T))
    replayed, _ = jax.jit(functools.partial(train_episode, cfg))(mem, ep)
    tr = got.transitions
    slots = N + np.arange(T)[::-1]                         # newest first
    np.testing.assert_array_equal(np.asarray(tr.reward)[slots], ep.reward)
    np.testing.assert_array_equal(np.asarray(tr.next_obs)[:, slots], ep.next_obs.T)
    np.testing.assert_array_equal(np.asarray(tr.terminated)[slots], ep.terminated)
    assert np.asarray(tr.present)[slots].all()
    exact = jax.jit(functools.partial(backup_memory, cfg))
    swept = exact(exact(replayed))
    np.testing.assert_allclose(np.asarray(got.values), np.asarray(swept.values), rtol=1e-6,
                               atol=1e-6)


def test_a_non_finite_target_is_refused_and_flagged():
    cfg = _config()
    mem = _memory(cfg)
    tr = mem.transitions
    mem = mem._replace(transitions=tr._replace(reward=tr.reward.at[7].set(jnp.inf)))
    out = jax.jit(functools.partial(backup_memory, cfg))(mem)
    assert int(out.flags) & FLAG_NONFINITE
    assert float(out.values[7]) == float(mem.values[7])
    assert np.all(np.isfinite(np.asarray(out.values)))


def test_a_memory_without_transitions_is_refused_by_name():
    cfg = _config(backup_sweeps=0)
    assert init_memory(cfg).transitions is None
    with pytest.raises(ValueError, match="backup_sweeps"):
        backup_memory(cfg, init_memory(cfg))


def test_a_checkpoint_keeps_the_transitions_bit_for_bit(tmp_path):
    cfg = _config()
    mem = _memory(cfg)
    path = save_checkpoint(tmp_path / "a.npz", cfg, mem)
    back = load_checkpoint(path).memory
    for k in StoredTransitions._fields:
        np.testing.assert_array_equal(np.asarray(getattr(back.transitions, k)),
                                      np.asarray(getattr(mem.transitions, k)))


@pytest.mark.parametrize("extra", [{}, {"clip_to_neighbours": True, "value_eps": 1e-3}])
def test_sweeps_through_a_plan_equal_the_float64_reference(extra):
    """Discrete actions: a plan's sweep is the exact sweep (coefficients times the stored
    values, the clip and the value scale applied after), and a second sweep through the same
    plan is the reference's second sweep (the points did not move)."""
    from hedger_jax.backup import backup_plan, backup_with_plan

    cfg = _config(**extra)
    mem = _memory(cfg)
    plan = jax.jit(functools.partial(backup_plan, cfg))(mem)
    sweep = jax.jit(functools.partial(backup_with_plan, cfg))
    once = sweep(mem, plan)
    if not extra:
        _assert_sweep(cfg, mem, once)
    exact = jax.jit(functools.partial(backup_memory, cfg))
    np.testing.assert_allclose(np.asarray(once.values), np.asarray(exact(mem).values),
                               rtol=2e-4, atol=2e-4)
    twice = sweep(once, plan)
    np.testing.assert_allclose(np.asarray(twice.values), np.asarray(exact(exact(mem)).values),
                               rtol=5e-4, atol=5e-4)


def test_a_plan_under_vmap_equals_each_memory_s_own():
    from hedger_jax.backup import backup_plan, backup_with_plan

    cfg = _config()
    mems = [_memory(cfg, seed=4), _memory(cfg, seed=5, reward_shift=-2.0)]
    batch = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *mems)
    out = jax.jit(jax.vmap(lambda m: backup_with_plan(cfg, m, backup_plan(cfg, m))))(batch)
    for b, m in enumerate(mems):
        _assert_sweep(cfg, m, jax.tree_util.tree_map(lambda x: x[b], out))


def test_a_continuous_plan_takes_the_max_over_the_search_grid():
    """Continuous actions: the plan's max runs over ``greedy_candidates`` (no refinement)."""
    from hedger_jax.backup import backup_plan, plan_targets

    cfg = _config(discrete_actions=None)
    mem = _memory(cfg)
    y, use = jax.jit(lambda m: plan_targets(cfg, m, backup_plan(cfg, m)))(mem)
    tr = jax.tree_util.tree_map(np.asarray, mem.transitions)
    q, _ = _grid_known_max(cfg, mem, tr.next_obs.T[:N])
    want = tr.reward[:N] + cfg.gamma * np.where(tr.terminated[:N], 0.0, q)
    np.testing.assert_allclose(np.asarray(y)[:N], want, rtol=1e-4, atol=1e-4)
    assert np.asarray(use).sum() == N - 1


def test_a_plan_reads_a_slot_overwritten_since_at_its_old_value():
    """Ring buffer: after a plan is built on a full memory, 10 new points overwrite the 10
    oldest slots. Every other row's target is the one the plan gave before (the overwritten
    neighbours read at their old values), and the overwritten rows are not backed up."""
    from hedger_jax.backup import backup_plan, overwritten, plan_targets
    from hedger_jax.memory import add_scaled

    cfg = _config(capacity=N, full_policy="overwrite_oldest")
    mem = _memory(cfg)
    plan = jax.jit(functools.partial(backup_plan, cfg))(mem)
    targets = jax.jit(functools.partial(plan_targets, cfg))
    before, use_before = targets(mem, plan)
    later = mem
    for i in range(10):
        later = add_scaled(cfg, later, jnp.full((3,), 0.15, jnp.float32), 50.0 + i, True,
                           (jnp.float32(9.0), jnp.full((2,), 0.1, jnp.float32), False))
    old = np.asarray(overwritten(later, plan))
    np.testing.assert_array_equal(np.flatnonzero(old), np.arange(10))
    after, use_after = targets(later, plan)
    np.testing.assert_array_equal(np.asarray(use_after), np.asarray(use_before) & ~old)
    np.testing.assert_allclose(np.asarray(after)[10:], np.asarray(before)[10:], rtol=1e-6)
