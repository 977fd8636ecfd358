"""What a ``Hedger`` learner runs with: its env, env params, ``HedgerConfig`` and ``RunConfig``
from what the user passed, the env's preset (``hedger_jax.presets``) filling in the rest --
for a Gymnasium env run by the host loop, the settings read from the task
(``hedger_jax.task_settings``).

``build`` checks every argument in the order ``Hedger`` documents them and raises
``ValueError`` / ``TypeError`` naming the argument.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Dict, Mapping, NamedTuple, Optional, Sequence

import numpy as np

from hedger_jax import environments
from hedger_jax.agent import RunConfig
from hedger_jax.config import HedgerConfig
from hedger_jax.presets import ENV_PRESETS, HOST_EVAL_EPISODES, preset
from hedger_jax.task_settings import task_settings
from hedger_jax.validation import InvalidInputError

__all__ = ["PRESETS", "Setup", "build", "preset_config", "preset_run_config", "preset_env_params",
           "scale_states", "ActionMap"]


class Setup(NamedTuple):
    """env: the functional env or ``environments.GymnasiumEnv``; name: its preset key;
    env_id: what ``save`` stores to rebuild it; from_instance: built from a user's instance;
    host_loop: the env runs in the host loop; env_params, config, run_config, seed,
    chunk_episodes: checked; actions: the ``ActionMap`` between the config's and the env's
    actions."""

    env: Any
    name: Optional[str]
    env_id: Optional[str]
    from_instance: bool
    host_loop: bool
    env_params: Any
    config: HedgerConfig
    run_config: RunConfig
    seed: int
    chunk_episodes: int
    actions: "ActionMap"


#: ``Hedger``'s ``preset`` choices.
PRESETS = ("auto", "task", "paper")


def build(env: Any, config: Optional[HedgerConfig], run_config: Any, *,
          seed: Any, env_params: Any, env_kwargs: Dict[str, Any], chunk_episodes: Any,
          overrides: Dict[str, Any], preset_name: str = "auto") -> Setup:
    """Resolve and check ``Hedger``'s arguments (see ``Hedger``) -> ``Setup``."""
    if preset_name not in PRESETS:
        raise ValueError(f"preset: must be one of {PRESETS}, got {preset_name!r}")
    resolved = environments.resolve_env(env, env_kwargs)
    env = resolved.env
    host_loop = isinstance(env, environments.GymnasiumEnv)
    settings = preset(resolved.name)
    if preset_name == "paper":
        settings = preset(None)
    task = preset_name == "task" or (preset_name == "auto" and host_loop
                                     and resolved.name not in ENV_PRESETS)
    run_overrides = None
    if isinstance(run_config, Mapping):          # overrides of the preset's run config
        run_overrides, run_config = dict(run_config), None
    if task and (config is None or run_config is None):
        if not host_loop:
            raise ValueError("preset: 'task' reads its settings from a Gymnasium env run by "
                             "the host loop; the project's JAX envs have their own presets")
        hedger, run = task_settings(env)                  # any other Gymnasium task
        settings = {"hedger": hedger, "run": run}
    if host_loop:
        if env_params is not None:
            raise ValueError("env_params: a Gymnasium env run by the host loop has no "
                             "params pytree")
    else:
        try:
            hash(env)
        except TypeError:
            raise TypeError(f"env: must be hashable (a static jit argument); "
                            f"{type(env).__name__} is not") from None
    if env_params is None:
        env_params = (preset_env_params(env, settings) if resolved.params is None
                      else resolved.params)
    if config is None:
        config = preset_config(env, env_params, settings, host_loop, overrides)
    else:
        config = _given_config(config, overrides)
    if run_config is None:
        run = {**settings["run"], **(run_overrides or {})}
        run_config = preset_run_config(env, {**settings, "run": run}, host_loop)
    if not isinstance(run_config, RunConfig):
        raise TypeError(f"run_config: expected a RunConfig, got {type(run_config).__name__}")
    if isinstance(seed, bool) or int(seed) != seed:
        raise ValueError(f"seed: must be an integer, got {seed!r}")
    if int(chunk_episodes) < 1:
        raise ValueError(f"chunk_episodes: must be >= 1, got {chunk_episodes}")
    return Setup(env, resolved.name, resolved.env_id, resolved.from_instance, host_loop,
                 env_params, config, run_config, int(seed), int(chunk_episodes),
                 ActionMap.build(config, env, host_loop))


def preset_env_params(env: Any, settings: Mapping[str, Any]) -> Any:
    """The env's default params with the preset's ``env_params`` overrides."""
    params = env.default_params()
    overrides = settings.get("env_params")
    return dataclasses.replace(params, **overrides) if overrides else params


def preset_config(env: Any, env_params: Any, settings: Mapping[str, Any], host_loop: bool,
                  overrides: Dict[str, Any]) -> HedgerConfig:
    """``HedgerConfig.for_env`` with the preset's settings, then ``overrides`` (which win); a
    host-loop env's action scale defaults to its ``default_action_scale``. The preset's
    ``state_scale_factors`` apply unless ``overrides`` set ``input_scale``."""
    kwargs = dict(settings["hedger"])
    if host_loop:
        kwargs.setdefault("action_scale", env.default_action_scale)
    kwargs.update(overrides)
    config = HedgerConfig.for_env(env, env_params, **kwargs)
    factors = settings.get("state_scale_factors")
    if factors is not None and "input_scale" not in overrides:
        config = scale_states(config, factors)
    return config


def scale_states(config: HedgerConfig, factors: Sequence[float]) -> HedgerConfig:
    """The config with its observation scaling multiplied by ``factors`` (S,) (the action's
    scaling unchanged)."""
    if len(factors) != config.state_dim:
        raise ValueError(f"state_scale_factors: expected {config.state_dim} factors, got "
                         f"{len(factors)}")
    factors = tuple(factors) + (1.0,) * config.action_dim
    return config.replace(input_scale=tuple(s * f for s, f in zip(config.input_scale, factors)))


def _given_config(config: Any, overrides: Dict[str, Any]) -> HedgerConfig:
    """A user's config with ``overrides`` (``HedgerConfig`` fields) applied."""
    if not isinstance(config, HedgerConfig):
        raise TypeError(f"config: expected a HedgerConfig, got {type(config).__name__}")
    if "action_scale" in overrides:
        raise ValueError("action_scale: only applies when config is None "
                         "(set input_scale in the HedgerConfig instead)")
    return config.replace(**overrides) if overrides else config


def preset_run_config(env: Any, settings: Mapping[str, Any], host_loop: bool) -> RunConfig:
    """``RunConfig`` with the preset's settings; a host-loop env evaluates
    ``HOST_EVAL_EPISODES`` episodes capped at its time limit."""
    kwargs = dict(settings["run"])
    if host_loop:
        kwargs.setdefault("eval_episodes", HOST_EVAL_EPISODES)
        kwargs.setdefault("eval_max_steps", env.max_steps)
    return RunConfig(**kwargs)


class ActionMap(NamedTuple):
    """Between HEDGER's action values and the actions the env's ``step`` takes: for a discrete
    env a ``Discrete`` index, for a continuous one the action vector itself.

    env_index: config action index -> env action index int64 (n,); start: the env's first
    ``Discrete`` index; values: the env's action values (m, A) (None, 0, None for continuous
    actions).
    """

    env_index: Optional[np.ndarray]
    start: int
    values: Optional[np.ndarray]

    @classmethod
    def build(cls, config: HedgerConfig, env: Any, host_loop: bool) -> "ActionMap":
        """Check the config against the env and map their actions. Raises ``ValueError``
        naming the mismatch."""
        space = env.action_space
        if config.state_dim != int(env.obs_dim):
            raise ValueError(f"config.state_dim {config.state_dim} != env obs_dim "
                             f"{env.obs_dim}")
        if config.action_dim != space.action_dim:
            raise ValueError(f"config.action_dim {config.action_dim} != env action_dim "
                             f"{space.action_dim}")
        if config.is_discrete != space.is_discrete:
            raise ValueError(f"config is {'discrete' if config.is_discrete else 'continuous'} "
                             f"but the env's action space is "
                             f"{'discrete' if space.is_discrete else 'continuous'}")
        if not config.is_discrete:
            return cls(None, 0, None)
        values = space.values_array()
        table = []
        for a in config.discrete_actions:
            match = np.flatnonzero(np.all(np.isclose(values.astype(np.float64), a, rtol=0,
                                                     atol=1e-6), axis=1))
            if match.size == 0:
                raise ValueError(f"config.discrete_actions: {a} is not an action of the env "
                                 f"({space.values})")
            table.append(int(match[0]))
        start = env.action_start if host_loop else 0
        return cls(np.asarray(table, np.int64), start, values)

    def env_actions(self, acts: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """Action values float32 (B, A) and their config indices int (B,) -> the env's
        actions: int64 (B,) indices (discrete) or float32 (B, A)."""
        if self.env_index is None:
            return acts.astype(np.float32)
        return self.env_index[idx] + self.start

    def action_values(self, action: Any) -> np.ndarray:
        """A discrete env's action indices, integer (...) -> action values (..., A). Raises
        ``InvalidInputError``."""
        idx = np.asarray(action)
        if not np.issubdtype(idx.dtype, np.integer):
            raise InvalidInputError(f"action: a discrete env takes integer indices, got dtype "
                                    f"{idx.dtype}")
        idx = idx - self.start
        if np.any((idx < 0) | (idx >= len(self.values))):
            raise InvalidInputError(f"action: index out of range [0, {len(self.values)}): "
                                    f"{idx}")
        return self.values[idx]
