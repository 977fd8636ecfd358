"""hedger_jax.kselect: the k smallest without sort or custom call, and mask compaction, against
NumPy references; which form each batch size takes; and the training loops they let XLA
compile into single kernels."""
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hedger_jax import kselect


#: The payload carried along with 96 values (position p carries 7 p + 3): one constant, so
#: the tests' programs over the same shapes are the same programs (compiled once).
_PAYLOAD = np.arange(96, dtype=np.int32) * 7 + 3


def _positions(payload):
    return (np.asarray(payload) - 3) // 7


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
    magnitudes = (10.0 ** rng.uniform(-40, 30, n)).astype(np.float32)    # 0 to 1e30
    return {"ties": ties, "spread": spread, "fewer than k finite": few,
            "magnitudes": magnitudes, "exactly k finite": np.where(
                np.arange(n) % 3 == 0, spread, np.inf).astype(np.float32),
            "zeros": np.zeros(n, np.float32), "subnormals": tiny,
            "ties with inf": np.where(rng.random(n) < 0.6, np.inf, ties).astype(np.float32)}


def _vmapped(fn, depth):
    for _ in range(depth):
        fn = jax.vmap(fn)
    return jax.jit(fn)


@pytest.mark.parametrize("shape", [(96,), (3, 96), (70, 96), (4, 20, 96)])
def test_smallest_k_matches_a_stable_sort(shape):
    """Single vectors, small and big vmapped batches, nested vmaps (4 x 20 = 80 members):
    the same positions as NumPy's stable sort, the values at those positions and
    the payload carried along."""
    rng = np.random.default_rng(0)
    k = 32
    fn = _vmapped(lambda v: kselect.smallest_k(v, jnp.asarray(_PAYLOAD), k), len(shape) - 1)
    for name, base in _cases(rng, int(np.prod(shape))).items():
        values = base.reshape(shape)
        got_v, got_p = (np.asarray(a) for a in fn(jnp.asarray(values)))
        flat_v, flat_got_v, flat_got_p = (a.reshape(-1, a.shape[-1])
                                          for a in (values, got_v, got_p))
        for row, gv, gp in zip(flat_v, flat_got_v, flat_got_p):
            pos = _positions(gp)
            np.testing.assert_array_equal(np.sort(pos), _reference(row, k), err_msg=name)
            np.testing.assert_array_equal(gv, row[pos], err_msg=name)


@pytest.mark.parametrize("kernels", [True, False])
@pytest.mark.parametrize("members", [3, 70])
def test_inside_a_vmapped_cond_with_a_batched_predicate(monkeypatch, kernels, members):
    """``lax.cond`` with one predicate per vmapped member runs both branches on operands it
    broadcasts to the batch -- constants the branches close over included. A custom_vmap
    function that closes over an array constant then fails to trace (JAX refuses a batched
    constant): vmapped continuous-action training with the grid index did, through the
    exploration's cond. Every form (sort-free with the packed compaction, and top_k) traces
    there and gives the members' own answers."""
    monkeypatch.setattr(kselect, "cpu_kernels", lambda: kernels)
    rng = np.random.default_rng(members)
    values = jnp.asarray(rng.random((members, 96)).astype(np.float32))
    pred = jnp.asarray(rng.random(members) < 0.5)

    def f(p, v):
        return jax.lax.cond(
            p, lambda v: (kselect.smallest_k(v, jnp.arange(96), 5)[1].sum(),
                          kselect.true_positions(v < 0.5, jnp.arange(96))),
            lambda v: (jnp.int32(-1), jnp.zeros(96, jnp.int32)), v)

    got_sum, got_count = jax.jit(jax.vmap(f))(pred, values)
    for i in range(members):
        row = np.asarray(values[i])
        if bool(pred[i]):
            assert int(got_sum[i]) == int(np.sort(np.argsort(row, kind="stable")[:5]).sum())
            where = np.flatnonzero(row < 0.5)
            want = np.full(96, 96)
            want[:len(where)] = where
            np.testing.assert_array_equal(np.asarray(got_count[i]), want)
        else:
            assert int(got_sum[i]) == -1


def test_loop_kernel_form_avoids_top_k_at_every_batch_size(monkeypatch):
    """With loop kernels on (``HEDGER_JAX_LOOP_KERNELS=1``), single vectors and vmapped
    batches of any size (nested vmaps included) compile without XLA's TopK custom call or a
    sort; without loop kernels, or with ``kernel_form=False``, top_k."""
    monkeypatch.setattr(kselect, "cpu_kernels", lambda: True)
    kselect._smallest_k_fn.cache_clear()

    def hlo(depth, shape, **kw):
        f = lambda v: kselect.smallest_k(v, jnp.arange(96, dtype=jnp.int32), 16, **kw)  # noqa
        return _vmapped(f, depth).lower(jnp.zeros(shape, jnp.float32)).compile().as_text()

    for depth, shape in ((0, (96,)), (1, (11, 96)), (2, (4, 8, 96)), (1, (64, 96)),
                         (2, (8, 11, 96))):
        text = hlo(depth, shape)
        assert "TopK" not in text and " sort(" not in text, shape
    assert "TopK" in hlo(0, (96,), kernel_form=False)
    monkeypatch.setattr(kselect, "cpu_kernels", lambda: False)
    kselect._smallest_k_fn.cache_clear()
    assert "TopK" in hlo(0, (96,)) and "TopK" in hlo(1, (64, 96))
    kselect._smallest_k_fn.cache_clear()


def test_many_members_one_after_another_match_the_batched_search(monkeypatch):
    """From ``MAP_MEMBERS`` vmapped members on, the members are searched one after another
    (a scan in the program); the answers are bit for bit those of the batched search (forced
    by a huge ``MAP_MEMBERS``), for a flat and a nested vmap, and equal the stable sort's."""
    monkeypatch.setattr(kselect, "cpu_kernels", lambda: True)
    rng = np.random.default_rng(5)
    payload = jnp.asarray(_PAYLOAD)

    def run(shape, members_limit):
        monkeypatch.setattr(kselect, "MAP_MEMBERS", members_limit)
        kselect._smallest_k_fn.cache_clear()
        f = _vmapped(lambda v: kselect.smallest_k(v, payload, 32), len(shape) - 1)
        return [np.asarray(a) for a in f(jnp.asarray(values))]

    for shape in ((kselect.MAP_MEMBERS, 96), (4, 20, 96)):
        base = _cases(rng, int(np.prod(shape)))
        for name in ("spread", "ties with inf"):
            values = base[name].reshape(shape)
            mapped = run(shape, 64)
            batched = run(shape, 10 ** 9)
            for a, b in zip(mapped, batched):
                np.testing.assert_array_equal(a, b, err_msg=f"{shape} {name}")
            flat_v, flat_p = values.reshape(-1, 96), mapped[1].reshape(-1, 32)
            for row, gp in zip(flat_v, flat_p):
                np.testing.assert_array_equal(np.sort(_positions(gp)), _reference(row, 32))
    monkeypatch.setattr(kselect, "MAP_MEMBERS", 64)
    kselect._smallest_k_fn.cache_clear()
    jaxpr = str(jax.make_jaxpr(jax.vmap(lambda v: kselect.smallest_k(v, payload, 32)))(
        jnp.zeros((64, 96), jnp.float32)))
    assert "scan" in jaxpr
    kselect._smallest_k_fn.cache_clear()


@pytest.mark.parametrize("n", [1, 5, 31, 32, 33, 96, 300, 1000])
def test_true_positions_match_numpy(n):
    """Every rank r (negative, past the last True too) of masks of several densities, as
    single vectors and under one and two vmaps: the position of the (r + 1)-th True entry,
    n beyond the last; word borders (31, 32, 33) and a partial last word included."""
    rng = np.random.default_rng(n)
    masks = np.stack([rng.random(n) < p for p in (0.0, 0.03, 0.4, 0.97, 1.0, 0.5, 0.2, 0.7)])
    r = np.arange(-2, n + 3, dtype=np.int32)
    want = np.empty((len(masks), len(r)), np.int64)
    for i, m in enumerate(masks):
        where = np.flatnonzero(m)
        want[i] = [where[j] if 0 <= j < len(where) else n for j in r]
    fn = lambda m: kselect.true_positions(m, jnp.asarray(r))  # noqa: E731
    for depth, arr, w in ((0, masks[2], want[2]), (1, masks, want),
                          (2, masks.reshape(2, 4, n), want.reshape(2, 4, -1))):
        got = np.asarray(_vmapped(fn, depth)(jnp.asarray(arr)))
        neg = r < 0                          # unspecified for r < 0: callers mask those
        np.testing.assert_array_equal(got[..., ~neg], w[..., ~neg])


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
    with pytest.raises(ValueError, match="bool vector"):
        kselect.true_positions(jnp.zeros((2, 8), bool), jnp.arange(3))
    with pytest.raises(ValueError, match="bool vector"):
        kselect.true_positions(jnp.zeros((8,), jnp.int32), jnp.arange(3))


_REPLAY_SCRIPT = """
import jax, jax.numpy as jnp, numpy as np
from hedger_jax.config import HedgerConfig
from hedger_jax.memory import init_memory
from hedger_jax.train import Transition, train_episode
cfg = HedgerConfig(state_dim=2, action_dim=1, capacity=3000, bandwidth=0.05,
                   max_neighbours=16, neighbour_index="grid", index_levels=1)
# Compiled for the shapes only: an empty memory and episode have the filled ones' shapes.
mem = jax.eval_shape(lambda: init_memory(cfg))
T = 6
f32 = jax.ShapeDtypeStruct
ep = Transition(obs=f32((T, 2), jnp.float32), action=f32((T, 1), jnp.float32),
                reward=f32((T,), jnp.float32), next_obs=f32((T, 2), jnp.float32),
                terminated=f32((T,), jnp.bool_), valid=f32((T,), jnp.bool_))
fn = jax.jit(lambda m, e: train_episode(cfg, m, e)[0])
text = fn.lower(mem, ep).compile().as_text()
calls = [l for l in text.splitlines() if 'xla_cpu_small_call="true"' in l and " call(" in l]
outer = [l for l in calls if "jit(<lambda>)/while" in l
         and "body" not in l.split("op_name=")[-1].split('"')[1]]
print("TOPK", "TopK" in text, "KERNELS", len(calls), "REPLAY", len(outer))
"""


# In the full suite (~9 s, a fresh process): a property of the compiled program that only
# speed depends on (benchmarks/ measure it); the quick tier checks that the loop-kernel
# insertion stays exact (test_index.py).
@pytest.mark.full
def test_training_replay_compiles_into_one_kernel_with_loop_kernels():
    """The point of kselect: with ``HEDGER_JAX_LOOP_KERNELS=1`` (a fresh process: XLA reads
    its flags once), the reverse replay of an episode over a one-level grid has no TopK
    custom call, so XLA compiles the replay's own loop into a single kernel
    ("xla_cpu_small_call")."""
    from hedger_jax import cpu

    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["XLA_FLAGS"] = " ".join(cpu.flags(loop_kernels=True))
    out = subprocess.run([sys.executable, "-c", _REPLAY_SCRIPT], env=env, capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    words = out.stdout.split()
    got = dict(zip(words[::2], words[1::2]))
    assert got["TOPK"] == "False" and int(got["KERNELS"]) > 0 and int(got["REPLAY"]) >= 1, got
