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


def test_valid_edge_values_accepted():
    HedgerConfig(1, 1, alpha=0.0, gamma=0.0)
    HedgerConfig(1, 1, alpha=1.0, gamma=1.0)
    HedgerConfig(1, 1, capacity=1)
    HedgerConfig(1, 1, k_min=3, max_neighbours=3)
    HedgerConfig(1, 1, full_policy="overwrite_oldest")
    HedgerConfig(1, 1, full_policy="error")
    HedgerConfig(2, 1, discrete_actions=((-1.0,), (0.0,), (1.0,)))


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


def test_a_data_chosen_width_with_continuous_actions_warns(recwarn):
    import warnings

    from hedger_jax import ADAPTIVE, ADAPTIVE_CONTINUOUS, HedgerParams

    box = _FakeEnv([-1.2, -0.07], [0.5, 0.07], ActionSpace.box([-1.0], [1.0]))
    discrete = _FakeEnv([-1.2, -0.07], [0.5, 0.07], ActionSpace.discrete([-1.0, 0.0, 1.0]))
    with pytest.warns(UserWarning, match="continuous actions"):
        HedgerConfig.for_env(box, capacity=8, kernel_k=8, kernel_range=8.0)
    cfg = HedgerConfig.for_env(box, capacity=8, max_bandwidth=1.0)
    with pytest.warns(UserWarning, match="continuous actions"):
        HedgerParams.create(cfg, kernel_k=[0, 8])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        HedgerConfig.for_env(discrete, capacity=8, **ADAPTIVE)
        HedgerConfig.for_env(box, capacity=8, **ADAPTIVE_CONTINUOUS)
        HedgerParams.create(cfg, **ADAPTIVE_CONTINUOUS)
        HedgerParams.create(cfg, kernel_k=0)
    assert "kernel_k" not in ADAPTIVE_CONTINUOUS and ADAPTIVE_CONTINUOUS["value_eps"] > 0
