"""hedger_jax.kselect: the k smallest without sort or custom call, and prefix counts, against
NumPy references; which form each batch size takes; and the training loops they let XLA
compile into single kernels."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hedger_jax import kselect
from hedger_jax.config import HedgerConfig
from hedger_jax.memory import add_points, init_memory, refresh_index
from hedger_jax.runtime import loop_kernels_enabled
from hedger_jax.train import Transition, train_episode


def _reference(values: np.ndarray, k: int) -> np.ndarray:
    """Positions of the k smallest (ties: lower position first), as sorted positions."""
    order = np.argsort(values, kind="stable")
    return np.sort(order[:k])


def _cases(rng, n):
    ties = rng.integers(0, 6, n).astype(np.float32) * np.float32(0.25)
    spread = rng.random(n).astype(np.float32) ** 3
    few = np.full(n, np.inf, np.float32)
    few[rng.choice(n, 5, replace=False)] = rng.random(5)
    tiny = (rng.random(n) * 1e-38).astype(np.float32)               # subnormals
    return {"ties": ties, "spread": spread, "fewer than k finite": few,
            "zeros": np.zeros(n, np.float32), "subnormals": tiny,
            "ties with inf": np.where(rng.random(n) < 0.6, np.inf, ties).astype(np.float32)}


def _vmapped(fn, depth):
    for _ in range(depth):
        fn = jax.vmap(fn)
    return jax.jit(fn)


@pytest.mark.parametrize("shape", [(96,), (3, 96), (70, 96), (4, 20, 96)])
def test_smallest_k_matches_a_stable_sort(shape):
    """Single vectors, small and big vmapped batches, nested vmaps (4 x 20 = 80 members: the
    big form): the same positions as NumPy's stable sort, the values at those positions and
    the payload carried along."""
    rng = np.random.default_rng(0)
    k = 32
    for name, base in _cases(rng, int(np.prod(shape))).items():
        values = base.reshape(shape)
        payload = (np.arange(shape[-1], dtype=np.int32) * 7 + 3)
        fn = _vmapped(lambda v: kselect.smallest_k(v, jnp.asarray(payload), k), len(shape) - 1)
        got_v, got_p = (np.asarray(a) for a in fn(jnp.asarray(values)))
        flat_v, flat_got_v, flat_got_p = (a.reshape(-1, a.shape[-1])
                                          for a in (values, got_v, got_p))
        for row, gv, gp in zip(flat_v, flat_got_v, flat_got_p):
            pos = (gp - 3) // 7
            np.testing.assert_array_equal(np.sort(pos), _reference(row, k), err_msg=name)
            np.testing.assert_array_equal(gv, row[pos], err_msg=name)


def test_small_batches_avoid_top_k_and_big_ones_use_it():
    """With loop kernels on (``import hedger_jax`` sets the flag), single vectors and vmapped
    batches below ``BIG_BATCH`` compile without XLA's TopK custom call or a sort; bigger
    batches (nested vmaps counted together) use top_k; without loop kernels top_k always."""
    assert loop_kernels_enabled()
    f = lambda v: kselect.smallest_k(v, jnp.arange(96, dtype=jnp.int32), 16)   # noqa: E731
    x = jnp.zeros((96,), jnp.float32)

    def hlo(depth, shape):
        return _vmapped(f, depth).lower(jnp.zeros(shape, jnp.float32)).compile().as_text()

    for depth, shape in ((0, (96,)), (1, (11, 96)), (2, (4, 8, 96))):
        text = hlo(depth, shape)
        assert "TopK" not in text and " sort(" not in text, shape
    for depth, shape in ((1, (64, 96)), (2, (8, 11, 96))):
        assert "TopK" in hlo(depth, shape), shape
    old = kselect.loop_kernels_enabled
    try:
        kselect.loop_kernels_enabled = lambda: False
        fresh = lambda v: kselect.smallest_k(v, jnp.arange(96, dtype=jnp.int32), 16)  # noqa
        assert "TopK" in jax.jit(fresh).lower(x).compile().as_text()   # (a new trace)
    finally:
        kselect.loop_kernels_enabled = old


@pytest.mark.parametrize("n", [5, 64, 96, 300])
def test_exclusive_count_matches_cumsum(n):
    rng = np.random.default_rng(n)
    x = rng.random((70, n)) < 0.4
    want = np.cumsum(x, axis=1) - x
    for depth, arr in ((0, x[0]), (1, x[:3]), (1, x), (2, x[:64].reshape(8, 8, n))):
        got = _vmapped(kselect.exclusive_count, depth)(jnp.asarray(arr))
        np.testing.assert_array_equal(np.asarray(got), want[:len(arr.reshape(-1, n))]
                                      .reshape(arr.shape))


def test_nth_true_finds_each_true_position():
    rng = np.random.default_rng(3)
    x = rng.random(50) < 0.3
    incl = jnp.asarray(np.cumsum(x).astype(np.int32))
    r = jnp.arange(20, dtype=jnp.int32)
    got = np.asarray(kselect.nth_true(incl, r))
    where = np.flatnonzero(x)
    want = np.where(np.arange(20) < len(where), np.append(where, [50] * 20)[:20], 50)
    np.testing.assert_array_equal(got, want)


def test_bad_arguments_are_refused():
    v = jnp.zeros((8,), jnp.float32)
    with pytest.raises(ValueError, match="0 < k <= 8"):
        kselect.smallest_k(v, jnp.arange(8), 9)
    with pytest.raises(ValueError, match="two vectors"):
        kselect.smallest_k(jnp.zeros((2, 8)), jnp.zeros((2, 8)), 3)
    with pytest.raises(ValueError, match="vector"):
        kselect.exclusive_count(jnp.zeros((2, 8), bool))


@pytest.mark.parametrize("levels", [1, 2])
def test_training_replay_compiles_into_one_kernel(levels):
    """The point of kselect: the reverse replay of an episode over a grid-indexed memory (one
    level: rare top_k on overflow; two levels: top_k on every trip) has no TopK custom call,
    so XLA compiles its loop into a single kernel ("xla_cpu_small_call")."""
    cfg = HedgerConfig(state_dim=2, action_dim=1, capacity=3000, bandwidth=0.05,
                       max_neighbours=16, neighbour_index="grid", index_levels=levels)
    rng = np.random.default_rng(5)
    pts = rng.random((1500, 3)).astype(np.float32)
    mem = refresh_index(cfg, add_points(cfg, init_memory(cfg), jnp.asarray(pts[:, :2]),
                                        jnp.asarray(pts[:, 2:]), jnp.asarray(pts[:, 0])),
                        force=True)
    T = 6
    ep = Transition(obs=jnp.asarray(rng.random((T, 2)), jnp.float32),
                    action=jnp.asarray(rng.random((T, 1)), jnp.float32),
                    reward=jnp.full((T,), -1.0), next_obs=jnp.asarray(rng.random((T, 2)),
                                                                      jnp.float32),
                    terminated=jnp.zeros((T,), bool), valid=jnp.ones((T,), bool))
    text = jax.jit(lambda m, e: train_episode(cfg, m, e)[0]).lower(mem, ep).compile().as_text()
    assert "TopK" not in text
    assert 'xla_cpu_small_call="true"' in text
    # The replay's own loop (a scan over the episode) is one of the kernels.
    calls = [line for line in text.splitlines() if "xla_cpu_small_call" in line]
    assert any("jit(<lambda>)/while" in line and "body" not in line.split("op_name=")[-1]
               for line in calls), calls[:3]
