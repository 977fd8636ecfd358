"""Host-boundary input checks (hedger_jax.validation), config refusals, and the in-jit error
flags: a NaN reward through train_step -> FLAG_NONFINITE -> memory_check raises, memory intact."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hedger_jax.config import HedgerConfig
from hedger_jax.memory import (FLAG_FULL, FLAG_NONFINITE, MemoryFullError, NonFiniteValueError,
                               add_points, init_memory, memory_check)
from hedger_jax.train import Transition, train_step
from hedger_jax.validation import (InvalidInputError, action_indices, check_actions,
                                   check_array, check_key, check_memory, check_observations,
                                   check_rewards, check_transitions, config_differences)

DISC = HedgerConfig(2, 1, capacity=64, bandwidth=0.1, discrete_actions=((-1.0,), (0.0,), (1.0,)))
CONT = HedgerConfig(2, 1, capacity=64, bandwidth=0.1, action_low=(-1.0,), action_high=(1.0,))


# ----------------------------------------------------------------------------- configs
@pytest.mark.parametrize("kwargs, match", [
    (dict(bandwidth=0.0), r"bandwidth: must be a finite number > 0, got 0.0"),
    (dict(bandwidth=-0.1), r"bandwidth: must be a finite number > 0, got -0.1"),
    (dict(bandwidth=float("nan")), r"bandwidth: must be a finite number > 0"),
    (dict(k_min=2), r"k_min: must be >= the number of regression parameters \(dim \+ 1 = 4\), "
                    r"got 2"),
    (dict(capacity=0), r"capacity: must be >= 1, got 0"),
    (dict(full_policy="grow"), r"full_policy: must be one of"),
    (dict(alpha=1.5), r"alpha: must be in \[0, 1\], got 1.5"),
])
def test_config_refuses(kwargs, match):
    with pytest.raises(ValueError, match=match):
        HedgerConfig(2, 1, **kwargs)


# ----------------------------------------------------------------------------- arrays
def test_observations_single_and_batch():
    a, batched = check_observations(DISC, [0.1, 0.2])
    assert a.shape == (1, 2) and a.dtype == np.float32 and not batched
    a, batched = check_observations(DISC, np.zeros((5, 2), np.float64))
    assert a.shape == (5, 2) and a.dtype == np.float32 and batched


@pytest.mark.parametrize("obs, match", [
    (np.zeros(3), r"observation: expected last dimension 2, got shape \(3,\)"),
    (np.zeros((2, 2, 2)), r"observation: expected 1 or 2 dimensions, got shape \(2, 2, 2\)"),
    (0.5, r"observation: expected 1 or 2 dimensions, got shape \(\)"),
    ([0.1, np.nan], r"observation: 1 value\(s\) is NaN or inf; first at index \(1,\): nan"),
    ([[0.0, 0.0], [np.inf, 0.0]], r"observation: 1 value\(s\) is NaN or inf; first at index "
                                  r"\(1, 0\): inf"),
    ([1e39, 0.0], r"observation: 1 value\(s\) overflows float32; first at index \(0,\): 1e\+39"),
    (np.array(["a", "b"]), r"observation: expected a real numeric array, got dtype <U1"),
    (np.array([True, False]), r"observation: expected a real numeric array, got dtype bool"),
    ([[0.1, 0.2], [0.3]], r"observation: cannot be converted to an array"),
])
def test_observations_refused(obs, match):
    with pytest.raises(InvalidInputError, match=match):
        check_observations(DISC, obs)
    assert issubclass(InvalidInputError, ValueError)


def test_rewards():
    assert check_rewards([0.0, 1.0]).dtype == np.float32
    with pytest.raises(InvalidInputError, match=r"reward: 1 value\(s\) is NaN or inf; first at "
                                                r"index \(2,\): nan"):
        check_rewards([0.0, 1.0, np.nan])
    with pytest.raises(InvalidInputError, match=r"reward: 1 value\(s\) is NaN or inf; first at "
                                                r"index \(\): -inf"):
        check_rewards(-np.inf)


def test_actions_continuous_bounds():
    np.testing.assert_array_equal(check_actions(CONT, [[-1.0], [0.3], [1.0]]),
                                  np.array([[-1.0], [0.3], [1.0]], np.float32))
    with pytest.raises(InvalidInputError, match=r"action: 1 action\(s\) outside the bounds "
                                                r"\[\(-1.0,\), \(1.0,\)\]; first at index "
                                                r"\(1,\): \[1.5\]"):
        check_actions(CONT, [[0.0], [1.5]])
    with pytest.raises(InvalidInputError, match=r"action: 1 value\(s\) is NaN or inf"):
        check_actions(CONT, [[np.nan]])
    with pytest.raises(InvalidInputError, match=r"action: expected last dimension 1"):
        check_actions(CONT, np.zeros((3, 2)))


def test_actions_discrete_set():
    assert action_indices(DISC, [[-1.0], [1.0], [0.0]]).tolist() == [0, 2, 1]
    check_actions(DISC, np.float32([[1.0]]))
    with pytest.raises(InvalidInputError, match=r"action: 1 action\(s\) not in the discrete set "
                                                r"\(\(-1.0,\), \(0.0,\), \(1.0,\)\); first at "
                                                r"index \(1,\): \[0.5\]"):
        check_actions(DISC, [[1.0], [0.5]])
    with pytest.raises(InvalidInputError, match="continuous, it has no indices"):
        action_indices(CONT, [[0.0]])


def _transitions(T=4, E=2):
    rng = np.random.default_rng(0)
    valid = np.zeros((E, T), bool)
    valid[0, :3] = True
    valid[1, :] = True
    return Transition(obs=rng.uniform(size=(E, T, 2)).astype(np.float32),
                      action=np.ones((E, T, 1), np.float32),
                      reward=np.zeros((E, T), np.float32),
                      next_obs=rng.uniform(size=(E, T, 2)).astype(np.float32),
                      terminated=np.zeros((E, T), bool), valid=valid)


def test_transitions_ok_and_refused():
    tr = _transitions()
    out = check_transitions(DISC, tr)
    assert out.obs.dtype == np.float32 and out.valid.dtype == np.bool_
    with pytest.raises(InvalidInputError, match=r"transitions.reward: 1 value\(s\) is NaN or "
                                                r"inf; first at index \(1, 2\): nan"):
        check_transitions(DISC, tr._replace(reward=_set(tr.reward, (1, 2), np.nan)))
    with pytest.raises(InvalidInputError, match=r"transitions.action \(valid steps\): 1 "
                                                r"action\(s\) not in the discrete set"):
        check_transitions(DISC, tr._replace(action=_set(tr.action, (1, 0, 0), 0.25)))
    # An odd action on a padding step is not checked against the set.
    check_transitions(DISC, tr._replace(action=_set(tr.action, (0, 3, 0), 0.0)))
    with pytest.raises(InvalidInputError, match=r"transitions.reward: expected shape \(2, 4\) "
                                                r"\(from obs \(2, 4, 2\)\), got \(2, 3\)"):
        check_transitions(DISC, tr._replace(reward=tr.reward[:, :3]))
    with pytest.raises(InvalidInputError, match=r"transitions.valid: the valid steps of episode "
                                                r"\(0,\) are not a prefix"):
        check_transitions(DISC, tr._replace(valid=_set(tr.valid, (0, 1), False)))
    with pytest.raises(InvalidInputError, match=r"transitions.terminated: expected booleans "
                                                r"\(0/1\), got 2"):
        check_transitions(DISC, tr._replace(terminated=np.full((2, 4), 2)))
    with pytest.raises(InvalidInputError, match="not a Transition-like object"):
        check_transitions(DISC, {"obs": 1})


def _set(a, idx, v):
    a = np.array(a, copy=True)
    a[idx] = v
    return a


def test_check_array_bool_and_key():
    assert check_array("m", [0, 1], dtype=np.bool_).dtype == np.bool_
    k = check_key(jax.random.PRNGKey(3))
    assert k.dtype == np.uint32 and k.shape == (2,)
    assert check_key(jax.random.key(3)).shape == (2,)
    with pytest.raises(InvalidInputError, match=r"key: expected a raw PRNG key of shape \(2,\) "
                                                r"and dtype uint32"):
        check_key(np.zeros(3, np.uint32))


def test_check_memory():
    mem = init_memory(DISC)
    check_memory(DISC, mem)
    with pytest.raises(InvalidInputError, match=r"memory.points: expected shape \(3, 32\) for "
                                                r"dim=3, capacity=32, got \(3, 64\)"):
        check_memory(DISC.replace(capacity=32), mem)
    with pytest.raises(InvalidInputError, match=r"memory.size: must be in \[0, 64\], got 65"):
        check_memory(DISC, mem._replace(size=jnp.int32(65)))
    with pytest.raises(InvalidInputError, match=r"memory.head: must be in \[0, 64\), got 64"):
        check_memory(DISC, mem._replace(head=jnp.int32(64)))
    with pytest.raises(InvalidInputError, match=r"memory.values: expected dtype float32, got "
                                                r"float64"):
        check_memory(DISC, mem._replace(values=np.zeros(64)))
    bad = mem._replace(values=mem.values.at[0].set(jnp.nan), size=jnp.int32(1))
    with pytest.raises(InvalidInputError, match="memory.values: NaN/inf among the stored values"):
        check_memory(DISC, bad)


def test_config_differences():
    assert config_differences(DISC, DISC) == []
    assert config_differences(DISC, DISC.replace(capacity=8, alpha=0.5)) == ["capacity", "alpha"]


# ----------------------------------------------------------------------------- in-jit flags
_step = jax.jit(functools.partial(train_step, DISC))


def _memory_with_points():
    rng = np.random.default_rng(1)
    n = 20
    S = rng.uniform(0.4, 0.6, (n, 2)).astype(np.float32)
    A = rng.choice([-1.0, 0.0, 1.0], (n, 1)).astype(np.float32)
    V = rng.uniform(0, 1, n).astype(np.float32)
    return add_points(DISC, init_memory(DISC), S, A, V)


@pytest.mark.parametrize("field, bad", [("reward", np.nan), ("reward", np.inf),
                                        ("next_obs", np.nan),
                                        ("obs", np.inf), ("action", np.nan)])
def test_nonfinite_through_train_step(field, bad):
    mem = _memory_with_points()
    before = jax.tree_util.tree_map(np.asarray, mem)
    tr = Transition(obs=jnp.array([0.5, 0.5]), action=jnp.array([1.0]), reward=jnp.float32(0.0),
                    next_obs=jnp.array([0.51, 0.5]), terminated=jnp.bool_(False),
                    valid=jnp.bool_(True))
    val = getattr(tr, field)
    tr = tr._replace(**{field: jnp.asarray(val).at[...].set(bad) if val.ndim == 0
                        else val.at[0].set(bad)})
    after, _ = _step(mem, tr)
    assert int(after.flags) & FLAG_NONFINITE
    with pytest.raises(NonFiniteValueError, match="a NaN/inf value tried to enter the HEDGER "
                                                  "memory and was refused"):
        memory_check(after)
    # Nothing stored, nothing moved: the memory is not corrupted.
    for k in ("points", "values", "size", "head"):
        np.testing.assert_array_equal(np.asarray(getattr(after, k)), getattr(before, k))
    assert np.all(np.isfinite(np.asarray(after.values)))


def test_finite_step_is_clean_and_full_flag():
    cfg = DISC.replace(capacity=4)
    step = jax.jit(functools.partial(train_step, cfg))
    mem = init_memory(cfg)
    tr = Transition(jnp.array([0.5, 0.5]), jnp.array([1.0]), jnp.float32(0.0),
                    jnp.array([0.51, 0.5]), jnp.bool_(False), jnp.bool_(True))
    for _ in range(4):
        mem, _ = step(mem, tr)
    memory_check(mem)
    assert int(mem.flags) == 0 and int(mem.size) == 4
    points = np.asarray(mem.points).copy()
    mem, _ = step(mem, tr)
    assert int(mem.flags) & FLAG_FULL and int(mem.size) == 4
    np.testing.assert_array_equal(np.asarray(mem.points), points)
    with pytest.raises(MemoryFullError, match=r"the HEDGER memory is full \(capacity 4\)"):
        memory_check(mem)


# ------------------------------------------------------------------ trace-time checks
def test_the_functional_api_checks_shapes_when_traced():
    """Wrong shapes or dtypes raise InvalidInputError naming the argument and the expected
    shape while the function is traced: with and without jit, and under vmap."""
    import jax
    import jax.numpy as jnp

    from hedger_jax import (HedgerParams, Transition, add_points, greedy_action, init_memory,
                            predict, train_step)
    from hedger_jax.validation import InvalidInputError

    cfg = HedgerConfig(2, 1, capacity=64, discrete_actions=((-1.0,), (0.0,), (1.0,)))
    mem = init_memory(cfg)
    s, a = jnp.zeros(2), jnp.zeros(1)
    for fn in (lambda *x: predict(cfg, mem, *x), jax.jit(lambda *x: predict(cfg, mem, *x))):
        with pytest.raises(InvalidInputError, match=r"state: expected shape \(2,\), got \(3,\)"):
            fn(jnp.zeros(3), a)
        with pytest.raises(InvalidInputError, match=r"action: expected shape \(1,\)"):
            fn(s, jnp.zeros(()))
        with pytest.raises(InvalidInputError, match="action: expected a real number dtype"):
            fn(s, jnp.zeros(1, bool))
    with pytest.raises(InvalidInputError, match=r"state: expected shape \(2,\), got \(5, 2\)"):
        jax.vmap(lambda x: predict(cfg, mem, x, a))(jnp.zeros((4, 5, 2)))
    with pytest.raises(InvalidInputError, match="key: expected a PRNG key"):
        greedy_action(cfg, mem, s, jnp.zeros(3, jnp.uint32))
    t = Transition(obs=s, action=a, reward=jnp.zeros(()), next_obs=jnp.zeros(3),
                   terminated=jnp.bool_(False), valid=jnp.bool_(True))
    with pytest.raises(InvalidInputError, match=r"transition.next_obs: expected shape \(2,\)"):
        train_step(cfg, mem, t)
    with pytest.raises(InvalidInputError, match=r"values: expected shape \(4,\)"):
        add_points(cfg, mem, jnp.zeros((4, 2)), jnp.zeros((4, 1)), jnp.zeros(5))
    batch = HedgerParams.create(cfg, alpha=np.asarray([0.5, 0.8]))
    with pytest.raises(InvalidInputError, match=r"params.bandwidth: expected shape \(\)"):
        predict(cfg, mem, s, a, batch)                 # a batch of settings is for vmap
    # ... under which it passes the checks (traced only: the checks run at trace time).
    out = jax.eval_shape(jax.vmap(lambda p: predict(cfg, mem, s, a, p)), batch)
    assert out[0].shape == (2,)


def test_nan_inputs_inside_jit_are_dont_know_or_refused():
    """Documented NaN behaviour: a NaN query finds no neighbour ("don't know": the default
    value, known False); a NaN reward or observation in training is refused and flagged."""
    import jax
    import jax.numpy as jnp

    from hedger_jax import (FLAG_NONFINITE, Transition, add_points, init_memory, predict,
                            train_step)

    cfg = HedgerConfig(2, 1, capacity=64, bandwidth=0.2, default_value=0.25,
                       discrete_actions=((-1.0,), (0.0,), (1.0,)))
    rng = np.random.default_rng(0)
    mem = add_points(cfg, init_memory(cfg), jnp.asarray(rng.uniform(0, 1, (30, 2)), jnp.float32),
                     jnp.zeros((30, 1)), jnp.ones(30))
    value, known, n = jax.jit(lambda s: predict(cfg, mem, s, jnp.zeros(1)))(
        jnp.asarray([np.nan, 0.5], jnp.float32))
    assert float(value) == 0.25 and not bool(known) and int(n) == 0
    t = Transition(obs=jnp.full(2, 0.5), action=jnp.zeros(1), reward=jnp.float32(np.nan),
                   next_obs=jnp.full(2, 0.5), terminated=jnp.bool_(False),
                   valid=jnp.bool_(True))
    new, _ = jax.jit(lambda m: train_step(cfg, m, t))(mem)
    assert int(new.size) == 30 and int(new.flags) & FLAG_NONFINITE
    np.testing.assert_array_equal(np.asarray(new.values), np.asarray(mem.values))
