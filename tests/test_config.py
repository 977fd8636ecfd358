"""HedgerConfig: validation (ValueError naming the field), hashability, derived properties."""
import dataclasses
import math
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from hedger_jax import HedgerConfig, add_points, init_memory  # noqa: E402
from envs.spaces import ActionSpace  # noqa: E402


# ---------------------------------------------------------------- validation
_ACTS2 = ((-1.0, 0.0), (1.0, 0.0), (0.0, 1.0))

@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(bandwidth=0.0), "bandwidth"),
        (dict(bandwidth=-0.1), "bandwidth"),
        (dict(capacity=0), "capacity"),
        (dict(capacity=-5), "capacity"),
        (dict(k_min=2), "k_min"),  # dim = 2 -> k_min >= 3
        (dict(k_min=3, max_neighbours=2), "max_neighbours"),
        (dict(alpha=1.5), "alpha"),
        (dict(alpha=-0.1), "alpha"),
        (dict(gamma=1.01), "gamma"),
        (dict(gamma=-1.0), "gamma"),
        (dict(input_offset=(0.0,)), "input_offset"),
        (dict(input_offset=(0.0, 0.0, 0.0)), "input_offset"),
        (dict(input_scale=(1.0, 1.0, 1.0)), "input_scale"),
        (dict(action_low=(-1.0, -1.0)), "action_low"),
        (dict(action_high=(1.0, 1.0)), "action_high"),
        (dict(full_policy="drop_newest_silently"), "full_policy"),
        (dict(discrete_actions=((1.0, 2.0), (0.0, 0.0))), "discrete_actions"),
    ],
)
def test_invalid_values_raise_naming_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        HedgerConfig(1, 1, **kwargs)


def test_k_min_lower_bound_depends_on_dim():
    # state_dim 3 + action_dim 2 -> at least 6 regression parameters
    kw = dict(action_low=(-1.0, -1.0), action_high=(1.0, 1.0), discrete_actions=_ACTS2)
    with pytest.raises(ValueError, match="k_min"):
        HedgerConfig(3, 2, k_min=5, **kw)
    cfg = HedgerConfig(3, 2, k_min=6, **kw)
    assert cfg.k_min == 6


@pytest.mark.parametrize("kwargs", [
    dict(alpha=0.0, gamma=0.0), dict(alpha=1.0, gamma=1.0), dict(capacity=1),
    dict(k_min=3, max_neighbours=3), dict(full_policy="overwrite_oldest"),
    dict(full_policy="error"), dict(discrete_actions=((-1.0,), (0.0,), (1.0,))),
    dict(min_weight=1e-9, ivh_tol=0.0, value_eps=0.0),
])
def test_valid_edge_values_are_kept_as_given(kwargs):
    """Values on the edge of their ranges are accepted and stored as given (as Python numbers
    of the field's kind), and the config round-trips through replace."""
    cfg = HedgerConfig(1, 1, **kwargs)
    for name, value in kwargs.items():
        assert getattr(cfg, name) == value, name
        assert type(getattr(cfg, name)) is type(value), name
    assert cfg.replace() == cfg and HedgerConfig(1, 1).replace(**kwargs) == cfg


# ---------------------------------------------------------------- derived properties
def test_derived_defaults():
    cfg = HedgerConfig(2, 1, bandwidth=0.015)
    assert cfg.dim == 3
    assert cfg.k_min == 4
    assert cfg.k_thresh == pytest.approx(0.015 * math.sqrt(math.log(100.0)), rel=1e-12)
    cfg = HedgerConfig(2, 1, bandwidth=0.2, min_weight=0.05)
    assert cfg.k_thresh == pytest.approx(0.2 * math.sqrt(math.log(20.0)), rel=1e-12)
    cfg = HedgerConfig(3, 2, action_low=(-1.0, -1.0), action_high=(1.0, 1.0),
                       discrete_actions=_ACTS2)
    assert cfg.dim == 5 and cfg.k_min == 6


def test_explicit_k_thresh_and_k_min_override():
    cfg = HedgerConfig(2, 1, bandwidth=0.1, k_thresh=0.05, k_min=7, max_neighbours=16)
    assert cfg.k_thresh == pytest.approx(0.05)
    assert cfg.k_min == 7


# ---------------------------------------------------------------- hashability / static use
def test_frozen_and_hashable():
    a = HedgerConfig(2, 1, bandwidth=0.05, capacity=64)
    b = HedgerConfig(2, 1, bandwidth=0.05, capacity=64)
    c = HedgerConfig(2, 1, bandwidth=0.06, capacity=64)
    assert a == b and hash(a) == hash(b)
    assert a != c
    assert len({a, b, c}) == 2
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.bandwidth = 0.3  # type: ignore[misc]
    d = HedgerConfig(2, 1, discrete_actions=((-1.0,), (0.0,), (1.0,)))
    hash(d)


def test_config_is_usable_as_static_jit_argument():
    g = jax.jit(lambda c, x: x + c.bandwidth, static_argnums=0)
    a = HedgerConfig(1, 1, capacity=8, bandwidth=0.25)
    b = HedgerConfig(1, 1, capacity=8, bandwidth=0.25)  # equal config: cache hit, same answer
    assert float(g(a, jnp.float32(1.0))) == pytest.approx(1.25)
    assert float(g(b, jnp.float32(1.0))) == pytest.approx(1.25)


# ---------------------------------------------------------------- input scaling / for_env
def test_input_offset_and_scale_define_the_scaled_space():
    cfg = HedgerConfig(2, 1, capacity=4, input_offset=(1.0, -2.0, 0.5),
                       input_scale=(0.5, 2.0, 4.0))
    mem = init_memory(cfg)
    s = np.array([[3.0, -1.0], [1.0, -2.0]], np.float32)
    a = np.array([[0.75], [0.5]], np.float32)
    mem = add_points(cfg, mem, s, a, np.array([0.1, 0.2], np.float32))
    pts = np.asarray(mem.points)
    expect = ((np.concatenate([s, a], 1) - np.array([1.0, -2.0, 0.5])) *
              np.array([0.5, 2.0, 4.0])).T
    np.testing.assert_allclose(pts[:, :2], expect, rtol=1e-6, atol=1e-7)


class _FakeParams:
    pass


class _FakeEnv:
    """Minimal functional env: obs in [low, high], a discrete or box action space."""
    name = "fake"
    max_steps = 10

    def __init__(self, low, high, space):
        self._low = np.asarray(low, np.float32)
        self._high = np.asarray(high, np.float32)
        self.action_space = space
        self.obs_dim = len(low)
        self.action_dim = space.action_dim

    def default_params(self):
        return _FakeParams()

    def obs_bounds(self, params):
        return jnp.asarray(self._low), jnp.asarray(self._high)


@pytest.mark.parametrize("discrete", [True, False])
def test_for_env_scales_obs_to_unit_box_and_actions_by_action_scale(discrete):
    space = (ActionSpace.discrete([-1.0, 0.0, 1.0]) if discrete
             else ActionSpace.box([-2.0], [2.0]))
    env = _FakeEnv([-1.2, -0.07], [0.5, 0.07], space)
    cfg = HedgerConfig.for_env(env, action_scale=0.5, bandwidth=0.02, capacity=8)
    assert cfg.state_dim == 2 and cfg.action_dim == 1 and cfg.dim == 3
    assert cfg.bandwidth == pytest.approx(0.02)  # override honoured
    assert cfg.capacity == 8
    if discrete:
        assert cfg.discrete_actions is not None
        assert sorted(float(v[0]) for v in cfg.discrete_actions) == [-1.0, 0.0, 1.0]
    else:
        assert cfg.discrete_actions is None
        assert tuple(cfg.action_low) == pytest.approx((-2.0,))
        assert tuple(cfg.action_high) == pytest.approx((2.0,))
    mem = init_memory(cfg)
    s = np.array([[-1.2, -0.07], [0.5, 0.07], [-0.35, 0.0]], np.float32)
    a = np.array([[1.0], [-1.0], [0.0]], np.float32)
    mem = add_points(cfg, mem, s, a, np.zeros(3, np.float32))
    pts = np.asarray(mem.points)[:, :3].T
    np.testing.assert_allclose(pts[:, :2], [[0, 0], [1, 1], [0.5, 0.5]], atol=1e-5)
    np.testing.assert_allclose(pts[:, 2], [0.5, -0.5, 0.0], atol=1e-6)


def test_for_env_action_scale_bounds_spans_the_action_range_like_the_states():
    box = _FakeEnv([-1.2, -0.07], [0.5, 0.07], ActionSpace.box([-2.0], [0.5]))
    cfg = HedgerConfig.for_env(box, action_scale="bounds", capacity=8)
    np.testing.assert_allclose(cfg.input_scale[2:], [1 / 2.5])
    np.testing.assert_allclose(cfg.input_scale[:2], [1 / 1.7, 1 / 0.14])
    discrete = _FakeEnv([-1.2, -0.07], [0.5, 0.07], ActionSpace.discrete([-1.0, 0.0, 1.0]))
    assert HedgerConfig.for_env(discrete, action_scale="bounds", capacity=8).input_scale[2] \
        == pytest.approx(0.5)
    with pytest.raises(ValueError, match="action_scale"):
        HedgerConfig.for_env(box, action_scale="bound", capacity=8)




# ---------------------------------------------------------------- each setting declared once
# Several valid values for every field of HedgerConfig (a new field without values here fails
# test_every_field_has_values: add some).
_BASE = dict(state_dim=2, capacity=64, max_bandwidth=0.3)
_VALUES = {
    "state_dim": [1, 3], "action_dim": [1], "input_offset": [0.5, (0.1, -0.2, 0.3)],
    "input_scale": [2.0, (1.0, 0.5, 4.0)], "capacity": [1, 5000],
    "bandwidth": [0.01, 0.2], "k_thresh": [0.05, 0.5], "min_weight": [0.001, 0.5],
    "kernel_range": [1.0, 3.0], "bandwidth_k": [0, 4, 1024], "bandwidth_shrink": [True],
    "value_eps": [0.0, 1e-6], "k_min": [4, 9], "max_neighbours": [16, 64],
    "default_value": [-1.0, 2.5], "alpha": [0.0, 1.0], "gamma": [0.5, 0.99],
    "use_ivh": [False], "region_update": [False], "random_ties": [True],
    "guess_unknown": [True], "clip_to_neighbours": [True],
    "replay_floor": [True], "discrete_actions": [((-1.0,), (1.0,))],
    "action_low": [-2.0, (-0.5,)], "action_high": [3.0], "greedy_samples": [3, 21],
    "greedy_iters": [0, 4], "greedy_tol": [1e-5], "full_policy": ["overwrite_oldest"],
    "backup_sweeps": [0, 2],
    "ridge": [1e-4], "ivh_tol": [0.0, 0.5], "neighbour_index": ["brute", "grid"],
    "index_chunk": [8], "index_bounds": [((0, 1), (0, 2), (-1, 1))], "index_levels": [1, 3],
    "index_recent": [0, 64], "max_bandwidth": [0.4, 1.0],
}


def test_every_field_has_values():
    assert set(_VALUES) == {f.name for f in dataclasses.fields(HedgerConfig)}


@pytest.mark.parametrize("name", sorted(_VALUES))
def test_replace_equals_constructing_with_the_value(name):
    """For every field and several values: replace(f=v) is the config constructing with f=v
    gives (derived fields -- k_thresh, k_min, max_bandwidth, a broadcast input scaling --
    derived again), and their HedgerParams defaults agree leaf for leaf."""
    from hedger_jax import HedgerParams

    base = HedgerConfig(**_BASE)
    for value in _VALUES[name]:
        built = HedgerConfig(**{**_BASE, name: value})
        replaced = base.replace(**{name: value})
        assert replaced == built, (name, value)
        assert hash(replaced) == hash(built)
        for a, b in zip(HedgerParams.defaults(replaced), HedgerParams.defaults(built)):
            np.testing.assert_array_equal(a, b, err_msg=f"{name}={value!r}")


def test_a_data_chosen_width_widens_the_radius_whichever_way_it_is_set():
    """The issue that motivated one declaration: replace(bandwidth_k=4) gave half the
    selection radius that constructing with bandwidth_k=4 gives."""
    built = HedgerConfig(2, 1, kernel_range=2, bandwidth_k=4)
    assert HedgerConfig(2, 1, kernel_range=2).replace(bandwidth_k=4) == built
    assert built.k_thresh == pytest.approx(2 * 0.015 * math.sqrt(math.log(100.0)), rel=1e-12)


def test_an_explicit_derived_value_is_kept_by_replace():
    cfg = HedgerConfig(2, 1, k_thresh=0.1, k_min=6, max_bandwidth=0.5, input_scale=(1, 2, 3))
    new = cfg.replace(bandwidth=0.02, state_dim=2)
    assert (new.k_thresh, new.k_min, new.max_bandwidth, new.input_scale) == (
        0.1, 6, 0.5, (1.0, 2.0, 3.0))


def test_the_kinds_are_declared_once_and_params_follow_them():
    """HedgerParams' fields are exactly the traced fields of HedgerConfig and RunConfig, with
    the dtype of their declared kind; a static field is refused by create naming it."""
    from hedger_jax import HedgerParams, RunConfig, StaticFieldError
    from hedger_jax.settings import DTYPES, fields_of, spec

    cfg = HedgerConfig(**_BASE)
    assert HedgerParams._fields == fields_of(HedgerConfig) + fields_of(RunConfig)
    p = HedgerParams.create(cfg)
    for name, leaf in p._asdict().items():
        owner = HedgerConfig if name in HedgerConfig.__dataclass_fields__ else RunConfig
        kind = spec(owner, name).kind
        assert leaf.dtype == DTYPES[kind], name
        assert leaf.shape == ((cfg.dim,) if kind == "vector" else ()), name
    for name in fields_of(HedgerConfig, ("static",)):
        with pytest.raises(StaticFieldError, match=name):
            HedgerParams.create(cfg, **{name: getattr(cfg, name)})


@pytest.mark.parametrize("name", sorted(set(_VALUES) & set(
    __import__("hedger_jax").HedgerParams._fields)))
def test_params_create_equals_replace_equals_the_config_value(name):
    """For every traced field and several values: create(config, f=v), create(config)
    .replace(f=v) and the defaults of config.replace(f=v) are the same leaves."""
    from hedger_jax import HedgerParams

    base = HedgerConfig(**_BASE)
    for value in _VALUES[name]:
        if name == "k_min" and value > base.max_neighbours:
            continue
        created = HedgerParams.create(base, **{name: value})
        replaced = HedgerParams.create(base).replace(**{name: value})
        from_config = HedgerParams.defaults(base.replace(**{name: value}))
        for f, a, b, c in zip(HedgerParams._fields, created, replaced, from_config):
            np.testing.assert_array_equal(a, b, err_msg=f"{name}={value!r}: {f}")
            np.testing.assert_array_equal(a, c, err_msg=f"{name}={value!r}: {f}")
            assert a.dtype == b.dtype == c.dtype, (name, f)


def test_defaults_and_create_give_one_compiled_program():
    """Python numbers or arrays make no difference: the defaults' leaves are those of create,
    so a jitted function compiles once for both (and gives the same result)."""
    from hedger_jax import HedgerParams

    cfg = HedgerConfig(**_BASE)
    f = jax.jit(lambda p: p.bandwidth * p.input_scale + p.k_min + p.use_ivh)
    a = f(HedgerParams.defaults(cfg))
    b = f(HedgerParams.create(cfg))
    assert f._cache_size() == 1
    np.testing.assert_array_equal(a, b)


def test_run_config_declares_its_traced_fields():
    from hedger_jax import RunConfig
    from hedger_jax.settings import fields_of

    assert fields_of(RunConfig) == ("epsilon", "noise_std")
    with pytest.raises(ValueError, match="epsilon: must be in"):
        RunConfig(epsilon=1.5)
    with pytest.raises(ValueError, match="n_blocks"):
        RunConfig(n_blocks=-1)
    assert RunConfig(epsilon=1).epsilon == 1.0 and isinstance(RunConfig(epsilon=1).epsilon,
                                                               float)
