"""Determinism of a small ``make_train`` run on CPU: the same key gives bitwise-identical
results across runs; ``vmap`` over seeds agrees with separate calls; different keys differ;
``train`` equals ``init`` then ``run_block``.

The run is small and its memory (256 slots) uses the brute-force neighbour search, which
compiles about three times faster than the grid index; one test runs it with the grid index
(what memories of 512 slots and more use). ``test_evaluation.py`` uses the same ENV, CFG and
RUN, so the compilation cache serves its ``train``, ``init`` and ``run_block`` programs from
these.
"""
import dataclasses

import jax
import numpy as np
import pytest

from envs.mountain_car import MountainCar
from hedger_jax.agent import RunConfig, make_train
from hedger_jax.config import HedgerConfig

ENV = MountainCar(continuous=False)
CFG = HedgerConfig.for_env(ENV, capacity=256, bandwidth=0.05)
# Every query searches (reuse_neighbours=False): then ``train`` and the pieces are the same
# arithmetic, bit for bit (the test below). Training episodes are capped below evaluation's.
RUN = RunConfig(n_blocks=2, episodes_per_block=2, eval_episodes=6, eval_max_steps=80,
                train_max_steps=60, reuse_neighbours=False)


class Programs:
    """The jitted programs of one ``make_train`` (compiled on first use)."""

    def __init__(self, run):
        self.tr = make_train(ENV, CFG, run)
        self.train = jax.jit(self.tr.train)
        self.vtrain = jax.jit(jax.vmap(self.tr.train))
        self.init = jax.jit(self.tr.init)
        self.run_block = jax.jit(self.tr.run_block)

    def in_blocks(self, key, n_blocks):
        """``init`` then ``run_block`` n_blocks times -> (state, results stacked per block)."""
        state, first = self.init(key)
        blocks = [first]
        for _ in range(n_blocks):
            state, res = self.run_block(state)
            blocks.append(res)
        return state, jax.tree_util.tree_map(lambda *x: np.stack(x), *blocks)


@pytest.fixture(scope="module")
def programs():
    return Programs(RUN)


def _leaves(out):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(out)]


def _assert_bitwise(a, b, what):
    a, b = _leaves(a), _leaves(b)
    assert len(a) == len(b), what
    for i, (x, y) in enumerate(zip(a, b)):
        assert x.dtype == y.dtype and x.shape == y.shape, (what, i)
        assert x.tobytes() == y.tobytes(), (what, i)


def test_same_key_bitwise_identical(programs):
    key = jax.random.PRNGKey(42)
    first = programs.train(key)
    _assert_bitwise(first, programs.train(key), "train(42) twice")
    # The run did something: points were stored and evaluated.
    state, results = first
    assert int(state.memory.size) > 0 and results.points.shape == (RUN.n_blocks + 1,)


def test_vmap_over_seeds_matches_separate_calls(programs):
    keys = jax.random.split(jax.random.PRNGKey(7), 3)
    batched = _leaves(programs.vtrain(keys))
    for i in range(keys.shape[0]):
        for j, (x, y) in enumerate(zip(_leaves(programs.train(keys[i])), batched)):
            y = y[i]
            if np.issubdtype(x.dtype, np.floating):
                np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6,
                                           err_msg=f"seed {i}, leaf {j}")
            else:
                np.testing.assert_array_equal(x, y, err_msg=f"seed {i}, leaf {j}")


def test_different_keys_differ(programs):
    a, _ = programs.train(jax.random.PRNGKey(1))
    b, _ = programs.train(jax.random.PRNGKey(2))
    size = min(int(a.memory.size), int(b.memory.size))
    assert size > 0
    assert not np.array_equal(np.asarray(a.memory.points)[:, :size],
                              np.asarray(b.memory.points)[:, :size])


def test_train_equals_init_then_run_blocks(programs):
    """``train`` (one scan over the evaluations) and the runner's pieces give the same run,
    bit for bit, when every query searches (``reuse_neighbours=False``). With the replay
    reusing the rollout's neighbour sets (the default for large memories) the two programs are
    compiled with slightly different float32 arithmetic (XLA's fusion and FMA contraction),
    so only each is deterministic (next test)."""
    key = jax.random.PRNGKey(5)
    _assert_bitwise(programs.train(key), programs.in_blocks(key, RUN.n_blocks),
                    "train vs init + run_block")


def test_points_per_block_pieces_with_reused_neighbours_are_deterministic(programs):
    """The runner's pieces (what experiments run and resume) repeat bit for bit with the
    replay reusing neighbour sets (``reuse_neighbours=True``), and run as many blocks as
    ``train``. Their blocks are ``points_per_block`` long: each block trains whole episodes
    (of at most ``train_max_steps``) until it has reached its target, the last one
    overshooting it by less than an episode."""
    target = 100
    run = dataclasses.replace(RUN, reuse_neighbours=True, episodes_per_block=None,
                              points_per_block=target)
    pieces = Programs(run)
    key = jax.random.PRNGKey(5)
    a = pieces.in_blocks(key, run.n_blocks)
    _assert_bitwise(a, pieces.in_blocks(key, run.n_blocks), "pieces run twice")
    assert [x.shape for x in _leaves(programs.train(key))] == [x.shape for x in _leaves(a)]
    res = a[1]
    points, episodes = np.asarray(res.points), np.asarray(res.episodes)
    assert episodes[0] == 0                       # evaluation right after phase 1
    gained = np.diff(points)
    assert np.all(gained >= target)               # each block reaches its target ...
    # ... by whole episodes of at most train_max_steps (< target: at least two per block).
    assert np.all(gained < target + run.train_max_steps) and np.all(np.diff(episodes) >= 2)
    mean_len = np.asarray(res.train_steps_mean)[1:]
    np.testing.assert_allclose(mean_len * np.diff(episodes), gained, rtol=1e-6)


def test_grid_index_run_is_bitwise_repeatable():
    """The same run with the grid neighbour index (the quick tier's one whole run with it:
    its programs compile about three times slower): the index is built and refreshed as the
    memory grows, the run learns and evaluates, and it repeats bit for bit."""
    cfg = HedgerConfig.for_env(ENV, capacity=512, bandwidth=0.05)
    assert cfg.index_kind == "grid"
    train = jax.jit(make_train(ENV, cfg, RUN).train)
    key = jax.random.PRNGKey(42)
    first = train(key)
    _assert_bitwise(first, train(key), "grid-index train(42) twice")
    state, results = first
    assert state.memory.index is not None and int(state.memory.size) > 0
    assert np.all(np.asarray(results.flags) == 0)
    steps = np.asarray(results.evaluation.mean_steps)
    assert np.all((steps >= 1) & (steps <= RUN.eval_max_steps))
