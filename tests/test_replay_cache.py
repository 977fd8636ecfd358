"""The replay's reuse of the rollout's neighbour sets (``hedger_jax.replay_cache``): the merged
sets equal a fresh search of the grown memory, entry for entry, on random and adversarial
data (ties, points on the threshold, duplicates, crowded appends); every case it cannot
answer falls back to the search; and training with the records equals training without."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from hedger_jax import HedgerConfig
from hedger_jax.agent import (RunConfig, explore_action_recorded, rollout, train_prefix,
                              training_act)
from hedger_jax.memory import add_scaled, init_memory, refresh_index, select_neighbours
from hedger_jax.replay_cache import APPENDED_WIDTH, StepNeighbours, cached_neighbours

K = 8


def _cfg(kind, policy="error"):
    """One grid level (the search's levels are tests/test_index.py's concern; one level
    compiles faster)."""
    return HedgerConfig(2, 1, capacity=600, bandwidth=0.1, max_neighbours=K,
                        neighbour_index=kind, full_policy=policy, index_levels=1)


def _with_points(cfg, pts, size=None):
    """A memory holding the scaled points pts (n, 3) in slots [0, n), indexed."""
    n = len(pts)
    points = np.zeros((3, cfg.capacity), np.float32)
    points[:, :n] = np.asarray(pts, np.float32).T
    values = np.zeros(cfg.capacity, np.float32)
    values[:n] = np.random.default_rng(n).uniform(0, 1e-2, n)
    mem = init_memory(cfg)._replace(points=jnp.asarray(points), values=jnp.asarray(values),
                                    size=jnp.int32(n), head=jnp.int32(n % cfg.capacity))
    # index=None: refresh_index builds the index of every stored point from scratch.
    return _refresh(cfg, mem._replace(index=None)) if mem.index is not None else mem


@functools.lru_cache(maxsize=None)
def _refresher(cfg):
    return jax.jit(lambda m: refresh_index(cfg, m, force=True))


def _refresh(cfg, mem):
    return _refresher(cfg)(mem)


#: Rows every batch of appended points is padded to (skipped writes): one program per config.
_APPEND_ROWS = 64


@functools.lru_cache(maxsize=None)
def _append_fn(cfg):
    return jax.jit(lambda m, zs, write: jax.lax.fori_loop(
        0, zs.shape[0], lambda i, m: add_scaled(cfg, m, zs[i], jnp.float32(0.25), write[i]), m))


def _append(cfg, mem, pts):
    """Appends the scaled points pts (n, 3) one write at a time (not merged into the index)."""
    n = len(pts)
    assert n <= _APPEND_ROWS
    zs = np.zeros((_APPEND_ROWS, 3), np.float32)
    zs[:n] = pts
    return _append_fn(cfg)(mem, jnp.asarray(zs), jnp.asarray(np.arange(_APPEND_ROWS) < n))


def _memory(cfg, pts):
    return _with_points(cfg, pts)


def _packed(nb):
    return np.where(np.asarray(nb.mask), np.asarray(nb.indices), -1)


@functools.lru_cache(maxsize=None)
def _searcher(cfg):
    return jax.jit(lambda m, zs: jax.vmap(lambda z: select_neighbours(cfg, m, z))(zs))


def _search(cfg, mem):
    return functools.partial(_searcher(cfg), mem)


@functools.lru_cache(maxsize=None)
def _merger(cfg, width):
    return jax.jit(lambda m, zs, sets, size0, ok: cached_neighbours(
        cfg, m, zs, (sets, size0, ok, width),
        jax.vmap(lambda z: select_neighbours(cfg, m, z)), cfg.k_thresh))


def _merged(cfg, mem, zs, sets, size0, ok, width=64):
    """``cached_neighbours`` of the queries zs with the sets over size0 slots; ok: whether
    each set (bool (q,)), or every one (bool), is usable (passed as (q,): one program)."""
    ok = np.broadcast_to(np.asarray(ok, bool), (zs.shape[0],))
    return _merger(cfg, width)(mem, zs, jnp.asarray(sets), jnp.int32(size0), jnp.asarray(ok))


def _assert_same(a, b):
    np.testing.assert_array_equal(np.asarray(a.mask), np.asarray(b.mask))
    np.testing.assert_array_equal(_packed(a), _packed(b))
    np.testing.assert_array_equal(np.asarray(a.sqdist), np.asarray(b.sqdist))


def _scenario(seed, n_old=300, n_new=40):
    """Old points, queries and appended points built to stress the merge: a lattice (many
    equal distances), duplicates of old points, points at exactly the threshold from a
    query, and a cluster of appended points around some queries."""
    rng = np.random.default_rng(seed)
    cfg = _cfg("brute")
    r = np.float32(cfg.k_thresh)
    lattice = np.stack(np.meshgrid(np.arange(6), np.arange(6), np.arange(3)), -1).reshape(-1, 3)
    old = np.concatenate([rng.uniform(0, 1, (n_old - len(lattice), 3)),
                          0.3 + 0.02 * lattice]).astype(np.float32)
    queries = np.concatenate([rng.uniform(0, 1, (20, 3)), old[-10:],
                              0.3 + 0.02 * lattice[:6] + 0.01]).astype(np.float32)
    new = [queries[i] + rng.normal(0, 0.3 * r, 3) for i in rng.integers(0, len(queries), n_new)]
    new += [old[5], old[-1], queries[0] + np.float32([r, 0, 0]), queries[1] - np.float32([0, r, 0])]
    return old, queries, np.asarray(new, np.float32)


@pytest.mark.parametrize("kind", ["brute", "grid"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_merged_sets_equal_a_search_of_the_grown_memory(kind, seed):
    old, queries, new = _scenario(seed)
    cfg = _cfg(kind)
    m0 = _memory(cfg, old)
    m1 = _append(cfg, m0, new)   # appended, not merged: the recent list too
    zs = jnp.asarray(queries)
    cached = _packed(_search(cfg, m0)(zs))
    want = _search(cfg, m1)(zs)
    got = _merged(cfg, m1, zs, cached, m0.size, True, 64)
    _assert_same(got, want)
    assert np.mean(np.sum(cached >= 0, axis=1)) > 2       # the old points were found
    # The appends changed some sets (else the test would not test the merge).
    assert np.any(_packed(want) != cached)


def test_crowded_queries_and_windows_too_small_fall_back_to_the_search():
    old, queries, _ = _scenario(3)
    cfg = _cfg("grid")
    m0 = _memory(cfg, old)
    # More than APPENDED_WIDTH appended points near query 0: the merge cannot take them all.
    near = queries[0] + np.random.default_rng(0).normal(
        0, 0.2 * cfg.k_thresh, (APPENDED_WIDTH + 5, 3)).astype(np.float32)
    m1 = _append(cfg, m0, near)
    zs = jnp.asarray(queries)
    cached = _packed(_search(cfg, m0)(zs))
    want = _search(cfg, m1)(zs)
    _assert_same(_merged(cfg, m1, zs, cached, m0.size, True, 64), want)
    # More appended points than the window (64) holds (sets recorded 65 points back), or
    # garbage sets marked unusable, or a memory that is not the recorded one grown: the
    # search answers.
    garbage = np.zeros_like(cached)
    _assert_same(_merged(cfg, m1, zs, garbage, m1.size - 65, True, 64), want)
    _assert_same(_merged(cfg, m1, zs, garbage, m0.size, False, 64), want)
    _assert_same(_merged(cfg, m1, zs, garbage, m1.size + 1, True, 64), want)


def test_only_the_first_set_missing_searches_the_first_and_merges_the_rest():
    """The replay after a random exploratory action: K of (s_t, a_t) was never searched
    (``ok[0]`` False) while the candidates' sets were. Query 0 is searched, the others merged
    (garbage where a set is unusable must never be used); a garbage set marked usable would
    change the answer (so the test can fail)."""
    old, queries, new = _scenario(6)
    for kind in ("brute", "grid"):
        cfg = _cfg(kind)
        m0 = _memory(cfg, old)
        m1 = _append(cfg, m0, new)
        zs = jnp.asarray(queries)
        cached = _packed(_search(cfg, m0)(zs))
        want = _search(cfg, m1)(zs)
        sets = cached.copy()
        sets[0] = np.arange(K)                      # garbage: slots 0..K-1, not query 0's K
        ok = np.ones(len(queries), bool)
        ok[0] = False
        _assert_same(_merged(cfg, m1, zs, sets, m0.size, ok, 64), want)
        assert np.any(_packed(_merged(cfg, m1, zs, sets, m0.size, True, 64))[0]
                      != _packed(want)[0])
        # Another set missing (not only the first): every query is searched.
        sets[3] = np.arange(K)
        ok[3] = False
        _assert_same(_merged(cfg, m1, zs, sets, m0.size, ok, 64), want)


def test_overwrite_oldest_never_uses_cached_sets():
    old, queries, _ = _scenario(4)
    cfg = _cfg("brute", policy="overwrite_oldest")
    mem = _memory(cfg, old)
    zs = jnp.asarray(queries)
    want = _search(cfg, mem)(zs)
    garbage = np.zeros((zs.shape[0], K), np.int32)
    _assert_same(_merged(cfg, mem, zs, garbage, mem.size, True, 64), want)


def test_vmapped_memories_that_disagree_all_search():
    """Under vmap (seeds) members whose sets are and are not usable: every member gets the
    search's answer (``batch_cond(..., equal=True)`` runs only the search)."""
    old, queries, new = _scenario(5)
    cfg = _cfg("brute")
    m0 = _memory(cfg, old)
    m1 = _append(cfg, m0, new)
    zs = jnp.asarray(queries)
    cached = _packed(_search(cfg, m0)(zs))
    want = _search(cfg, m1)(zs)
    fn = jax.jit(jax.vmap(lambda sets, ok: cached_neighbours(
        cfg, m1, zs, (sets, m0.size, ok, 64), jax.vmap(lambda z: select_neighbours(cfg, m1, z)),
        cfg.k_thresh)))
    got = fn(jnp.stack([jnp.asarray(cached), jnp.zeros_like(cached)]), jnp.asarray([True, False]))
    for i in range(2):
        _assert_same(jax.tree_util.tree_map(lambda x: x[i], got), want)
    # Per-query flags: one member with every set, one with all but the first (garbage there).
    first_missing = np.array(cached)
    first_missing[0] = np.arange(K)
    ok = np.ones((2, len(queries)), bool)
    ok[1, 0] = False
    got = fn(jnp.stack([jnp.asarray(cached), jnp.asarray(first_missing)]), jnp.asarray(ok))
    for i in range(2):
        _assert_same(jax.tree_util.tree_map(lambda x: x[i], got), want)


# Quick: brute force (its programs compile about six times faster than the grid's). The
# merge is the same code for both; test_merged_sets_equal_a_search_of_the_grown_memory[*-grid]
# checks it against the grid search, tests/test_index.py the grid against brute force. The
# grid and the continuous case in the full suite.
@pytest.mark.parametrize("env_name,kind", [
    ("mountain_car_discrete", "brute"),
    pytest.param("mountain_car_discrete", "grid", marks=pytest.mark.full),
    pytest.param("mountain_car_continuous", "brute", marks=pytest.mark.full)])
def test_training_with_the_records_equals_training_without(env_name, kind):
    """Episodes from a seeded memory: the rollout records its sets, the replay merges them.
    Same memory as the replay that searches every query (the same sets; the values to
    float32 rounding). One program: ``use`` (traced) hands the replay either the records or
    none (``train_prefix(..., None)``, selected by ``lax.cond``)."""
    env = envs.make(env_name)
    params = env.default_params()
    kw = dict(action_scale=0.1) if "continuous" in env_name else {}
    cfg = HedgerConfig.for_env(env, capacity=12_000, bandwidth=0.015, neighbour_index=kind,
                               **kw)
    rng = np.random.default_rng(0)
    n = 10_000                          # dense enough that most greedy searches know a value
    z = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    z[:, 2] = rng.choice([-1.0, 0.0, 1.0], n) if cfg.is_discrete else rng.uniform(-0.1, 0.1, n)
    mem = _with_points(cfg, z)
    run = RunConfig(reuse_neighbours=True)      # on below REUSE_MIN_CAPACITY too

    @jax.jit
    def episodes(memory, key, use):
        def one(m, k):
            k1, k2 = jax.random.split(k)
            obs0, s0 = env.reset(k1, params)

            ep, length, rec = rollout(env, params, training_act(cfg, run, m), k2, 100, obs0, s0)
            m = jax.lax.cond(use, lambda m: train_prefix(cfg, m, ep, length, rec),
                             lambda m: train_prefix(cfg, m, ep, length, None), m)
            return refresh_index(cfg, m), (length, jnp.sum(rec.has_chosen & rec.has_candidates))
        return jax.lax.scan(one, memory, jax.random.split(key, 4))

    a, (lengths, cached) = episodes(mem, jax.random.PRNGKey(1), False)
    b, _ = episodes(mem, jax.random.PRNGKey(1), True)
    assert int(jnp.sum(cached)) > 0.5 * int(jnp.sum(lengths))   # most steps used the cache
    np.testing.assert_array_equal(np.asarray(a.points), np.asarray(b.points))
    assert int(a.size) == int(b.size) == n + int(jnp.sum(lengths))
    np.testing.assert_allclose(np.asarray(a.values), np.asarray(b.values), rtol=1e-6, atol=1e-9)


def test_the_record_holds_the_sets_of_the_queries_it_names():
    """A greedy step records K of the action taken and of every greedy candidate (each the
    search's); a random exploratory step (epsilon 1) records none. One program: the step is
    made greedy by the traced ``greedy_only``."""
    env = envs.make("mountain_car_continuous")
    cfg = HedgerConfig.for_env(env, capacity=3000, bandwidth=0.015, action_scale=0.1,
                               neighbour_index="brute")
    rng = np.random.default_rng(1)
    obs = jnp.asarray([-0.5, 0.0], jnp.float32)
    from hedger_jax.memory import scale_inputs
    s = np.asarray([-0.5, 0.0]) + rng.normal(0, [0.05, 0.004], (400, 2))
    a = rng.uniform(-1, 1, (400, 1))
    mem = _with_points(cfg, np.asarray(scale_inputs(cfg, jnp.asarray(s, jnp.float32),
                                                    jnp.asarray(a, jnp.float32))))
    step = jax.jit(lambda k, greedy: explore_action_recorded(
        cfg, RunConfig(epsilon=1.0), mem, obs, k, greedy_only=greedy))
    search = jax.jit(jax.vmap(lambda a: select_neighbours(cfg, mem, scale_inputs(cfg, obs, a))))
    for greedy, key in ((True, 3), (False, 4)):
        action, rec = step(jax.random.PRNGKey(key), greedy)
        if not greedy:                        # a random step searched nothing
            assert not bool(rec.has_candidates) and not bool(rec.has_chosen)
            continue
        assert bool(rec.has_candidates) and bool(rec.has_chosen)
        grid = jnp.linspace(-1.0, 1.0, cfg.greedy_samples, dtype=jnp.float32)[:, None]
        want = search(jnp.concatenate([action[None], grid]))
        np.testing.assert_array_equal(np.asarray(rec.chosen), _packed(want)[0])
        np.testing.assert_array_equal(np.asarray(rec.candidates), _packed(want)[1:])
        assert int(rec.size) == int(mem.size)


def test_rollout_refuses_an_act_whose_outputs_do_not_match_its_record_like():
    env = envs.make("mountain_car_discrete")
    params = env.default_params()
    obs0, s0 = env.reset(jax.random.PRNGKey(0), params)

    def act3(k, obs, st):                       # a record, but no record_like to size it
        return jnp.zeros((1,)), st, jnp.zeros(())

    with pytest.raises(ValueError, match="record_like"):
        rollout(env, params, act3, jax.random.PRNGKey(1), 5, obs0, s0)


def _rollout_keeps_records(cfg, run):
    """Whether an episode's rollout with ``training_act`` returns the sets its greedy
    searches found (for the replay to reuse), read from its outputs (traced, not run)."""
    env = envs.make("mountain_car_discrete")
    params = env.default_params()

    def episode(memory, key):
        obs0, s0 = env.reset(key, params)
        return rollout(env, params, training_act(cfg, run, memory), key, 3, obs0, s0)

    memory = jax.eval_shape(functools.partial(init_memory, cfg))
    out = jax.eval_shape(episode, memory, jax.random.PRNGKey(0))
    if len(out) == 2:
        return False
    assert isinstance(out[2], StepNeighbours) and out[2].chosen.shape == (3, cfg.max_neighbours)
    return True


def test_reuse_is_automatic_from_the_minimum_capacity():
    """The rollout records the greedy searches' sets from ``REUSE_MIN_CAPACITY`` slots on
    (``reuse_neighbours=None``), or as ``reuse_neighbours`` says; never for a ring buffer."""
    from hedger_jax.replay_cache import REUSE_MIN_CAPACITY
    env = envs.make("mountain_car_discrete")
    # Brute force (cheaper to trace): the choice depends on the capacity and policy only.
    small = HedgerConfig.for_env(env, capacity=1000, neighbour_index="brute")
    big = HedgerConfig.for_env(env, capacity=REUSE_MIN_CAPACITY, neighbour_index="brute")
    assert not _rollout_keeps_records(small, RunConfig())
    assert _rollout_keeps_records(small, RunConfig(reuse_neighbours=True))
    assert _rollout_keeps_records(big, RunConfig())
    assert not _rollout_keeps_records(big, RunConfig(reuse_neighbours=False))
    ring = big.replace(full_policy="overwrite_oldest")
    assert not _rollout_keeps_records(ring, RunConfig(reuse_neighbours=True))
