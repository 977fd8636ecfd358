"""Which environment a ``Hedger`` learner runs on, and how a Gymnasium env is presented to it.

``resolve_env`` turns what a user passes to ``Hedger`` into one of two kinds:

* a *functional* env (``envs.base``): the project's JAX envs, by ``envs.make`` name, by their
  Gymnasium id (``GYM_IDS``), as a ``gymnasium.Env`` whose ``unwrapped`` is the project's
  adapter (``envs.gym_adapter.FunctionalGymEnv``: its functional env and params are used), or
  any functional env object. Whole episodes then run inside jitted code.
* a ``GymnasiumEnv``: any other Gymnasium env (an id for ``gymnasium.make``, or an instance)
  whose observation space is a ``Box`` of shape (S,) and whose action space is ``Discrete``
  or a ``Box`` of shape (1,). ``Hedger`` drives it from the host (``hedger_jax.host_loop``).

How a Gymnasium env is presented to HEDGER (``GymnasiumEnv``):

* Actions. ``Discrete(n, start)``: HEDGER's action values are (0,), (1,), ..., (n-1,), raw
  (unit spacing keeps different actions' points apart in the distance); the env receives
  ``start + i``. A ``Box`` of shape (1,) with finite bounds: a continuous action in
  [low, high], scaled by ``0.2 / (high - low)`` so that the whole range spans 0.2 in scaled
  units (as the continuous mountain-car preset: [-1, 1] x 0.1), unless ``action_scale`` is
  given.
* Observations are scaled to [0, 1] from the ``Box`` bounds; a dimension whose bound is
  unbounded (±inf, or a magnitude of at least 1e6) takes its range from 2,000 random-action
  steps of a seeded copy of the env (``envs.scaling``: min/max widened by 10 % per side, a
  constant dimension a unit range).
* Time limit. ``max_steps`` is the env's ``TimeLimit`` (or its spec's
  ``max_episode_steps``); an env without one is capped at ``DEFAULT_MAX_STEPS`` by the host
  loop. A transition's ``terminated`` is Gymnasium's ``terminated`` only: a truncation (the
  env's or the cap's) ends the episode but is never a terminal state.

Layering: this module and the learner's modules are the only parts of ``hedger_jax`` that know
``envs`` and Gymnasium; both are imported lazily, so ``import hedger_jax`` imports neither.
The host loop's pieces (``run_episode``, ``explore_step``, ...) live in ``host_loop`` and are
re-exported here.
"""
from __future__ import annotations

import copy
from typing import Any, Callable, Dict, NamedTuple, Optional, Tuple

import numpy as np

from hedger_jax.host_loop import (EpisodeBuffer, EpisodeResult,  # noqa: F401 (re-exported)
                                  explore_step, greedy_step, refresh, replay_episode,
                                  run_episode, seed_from_key)

__all__ = ["GYM_IDS", "GOAL_TASKS", "DEFAULT_MAX_STEPS", "ACTION_SPAN", "GymnasiumEnv", "ResolvedEnv",
           "resolve_env", "make_env", "is_functional_name", "check_spaces", "EpisodeBuffer",
           "run_episode", "explore_step", "greedy_step", "replay_episode", "refresh",
           "seed_from_key", "sample_observations"]

#: Gymnasium ids (``envs.gym_adapter``) -> ``envs.make`` names.
GYM_IDS = {
    "HedgerMountainCar-v0": "mountain_car_discrete",
    "HedgerMountainCarContinuous-v0": "mountain_car_continuous",
    "HedgerCorridor-v0": "corridor",
}
#: Gymnasium tasks whose termination is reaching the goal (elsewhere, e.g. CartPole's falling
#: pole, terminating is failing): only there does ``evaluate`` report a ``success_rate``.
GOAL_TASKS = frozenset({"MountainCar-v0", "MountainCarContinuous-v0", "Acrobot-v1"})
#: Episode cap of the host loop for a Gymnasium env without a time limit.
DEFAULT_MAX_STEPS = 1000
#: Scaled width of a continuous action range (``action_scale = ACTION_SPAN / (high - low)``).
ACTION_SPAN = 0.2


def is_functional_name(name: str) -> bool:
    """Whether ``name`` is one of the project's JAX envs (a ``GYM_IDS`` id or ``envs.make``
    name), which run on the jitted fast path."""
    import envs

    return name in GYM_IDS or name in envs.NAMES


def make_env(env_id: str, **env_kwargs: Any):
    """A functional env from a Gymnasium id (``GYM_IDS``) or an ``envs.make`` name.

    Returns (env, name) where name is the ``envs.make`` name. Raises ``ValueError`` for an
    unknown id.
    """
    import envs

    if not isinstance(env_id, str):
        raise TypeError(f"env id must be a string, got {type(env_id).__name__}")
    name = GYM_IDS.get(env_id, env_id)
    try:
        return envs.make(name, **env_kwargs), name
    except ValueError as exc:
        raise ValueError(f"unknown environment {env_id!r}: not a registered Gymnasium id "
                         f"({sorted(GYM_IDS)}) nor an envs.make name ({exc})") from None


# ------------------------------------------------------------------------------------------
# The Gymnasium env as HEDGER sees it
# ------------------------------------------------------------------------------------------
def check_spaces(observation_space: Any, action_space: Any) -> None:
    """Refuse spaces the host loop cannot handle, naming the space and what is supported.

    Supported: observation ``Box`` of shape (S,); action ``Discrete`` or ``Box`` of shape (1,)
    with finite bounds. Raises ``ValueError``.
    """
    from gymnasium import spaces

    supported = ("HEDGER supports a Box observation space of shape (S,) and a Discrete or "
                 "one-dimensional Box (shape (1,)) action space")
    if not isinstance(observation_space, spaces.Box):
        raise ValueError(f"unsupported observation space {observation_space}: {supported} "
                         "(flatten a Dict/Tuple space with gymnasium.wrappers.FlattenObservation)")
    if len(observation_space.shape) != 1:
        raise ValueError(f"unsupported observation space {observation_space} (shape "
                         f"{observation_space.shape}): {supported} (flatten it with "
                         "gymnasium.wrappers.FlattenObservation)")
    if isinstance(action_space, spaces.Discrete):
        return
    if not isinstance(action_space, spaces.Box):
        raise ValueError(f"unsupported action space {action_space}: {supported}")
    if action_space.shape != (1,):
        raise ValueError(f"unsupported action space {action_space} (shape "
                         f"{action_space.shape}): {supported}; HEDGER's continuous greedy "
                         "search is one-dimensional")
    if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
        raise ValueError(f"unsupported action space {action_space}: a continuous action needs "
                         "finite bounds")


def _time_limit(env: Any) -> Optional[int]:
    """The episode cap of a Gymnasium env: its outermost ``TimeLimit``, else its spec's."""
    import gymnasium
    from gymnasium.wrappers import TimeLimit

    e = env
    while isinstance(e, gymnasium.Wrapper):
        if isinstance(e, TimeLimit):
            return int(e._max_episode_steps)
        e = e.env
    spec = getattr(env, "spec", None)
    steps = getattr(spec, "max_episode_steps", None)
    return None if steps is None else int(steps)


def sample_observations(env: Any, n: int, seed: int) -> np.ndarray:
    """Observations seen while taking ``n`` uniformly random actions in ``env`` (reset with
    ``seed``, action space seeded with ``seed``, episodes restarted when they end): the
    observation each step acts from -> float64 (n, S)."""
    env.action_space.seed(seed)
    obs, _ = env.reset(seed=seed)
    out = np.empty((n,) + np.shape(obs), np.float64)
    for i in range(n):
        out[i] = obs
        obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            obs, _ = env.reset()
    return out


class GymnasiumEnv:
    """A Gymnasium env that ``Hedger`` drives from the host (see the module doc).

    It carries the static description ``HedgerConfig.for_env`` and ``Hedger`` read from a
    functional env: ``name``, ``obs_dim``, ``action_space`` (``envs.spaces.ActionSpace``:
    the values (0,) ... (n-1,) for ``Discrete(n)``, the box for a ``Box``), ``max_steps``,
    ``default_params()`` (None) and ``obs_bounds(params)`` (the scaling range).

    Args:
      env: a ``gymnasium.Env`` (spaces checked by ``check_spaces``).
      env_id: the Gymnasium id it was made from (None for a user's instance).
      make_copy: () -> a fresh env like ``env``, for the observation samples of the scaling
        range; default ``copy.deepcopy(env)`` (``env`` itself if it cannot be copied).

    Attributes: ``gym_env``, ``env_id``, ``name`` (the id, else the class name),
    ``goal_on_termination`` (the id, or the instance's spec id, is one of ``GOAL_TASKS``),
    ``action_start`` (``Discrete.start``; 0 for a Box), ``default_action_scale``
    (1 for ``Discrete``, ``ACTION_SPAN / (high - low)`` for a Box).
    """

    def __init__(self, env: Any, env_id: Optional[str] = None,
                 make_copy: Optional[Callable[[], Any]] = None):
        from gymnasium import spaces

        from envs.spaces import ActionSpace

        check_spaces(env.observation_space, env.action_space)
        self.gym_env = env
        self.env_id = env_id
        self.name = env_id or type(env.unwrapped).__name__
        spec_id = getattr(getattr(env, "spec", None), "id", None)
        self.goal_on_termination = (env_id or spec_id) in GOAL_TASKS
        self.obs_dim = int(env.observation_space.shape[0])
        space = env.action_space
        if isinstance(space, spaces.Discrete):
            self.action_space = ActionSpace.discrete(np.arange(int(space.n), dtype=np.float64))
            self.action_start = int(space.start)
            self.default_action_scale = 1.0
        else:
            low, high = float(space.low[0]), float(space.high[0])
            self.action_space = ActionSpace.box(low, high)
            self.action_start = 0
            self.default_action_scale = ACTION_SPAN / (high - low)
        limit = _time_limit(env)
        self.has_time_limit = limit is not None
        self.max_steps = DEFAULT_MAX_STEPS if limit is None else limit
        self._make_copy = make_copy
        self._bounds: Optional[Tuple[np.ndarray, np.ndarray]] = None

    def __repr__(self) -> str:
        return f"GymnasiumEnv({self.name!r})"

    def default_params(self) -> None:
        """A Gymnasium env has no params pytree."""
        return None

    def obs_bounds(self, params: Any = None) -> Tuple[np.ndarray, np.ndarray]:
        """The scaling range: the ``Box`` bounds, unbounded dimensions from random-action
        samples (``envs.scaling``) -> (low, high) float32 (S,). Computed once."""
        del params
        if self._bounds is None:
            from envs import scaling

            space = self.gym_env.observation_space
            low = np.asarray(space.low, np.float64)
            high = np.asarray(space.high, np.float64)
            if np.any(np.asarray(scaling.unbounded(low, high))):
                samples = sample_observations(self.fresh_copy(), scaling.SAMPLE_STEPS,
                                              scaling.SAMPLE_SEED)
                low, high = scaling.scaling_bounds(low, high, samples)
            self._bounds = (np.asarray(low, np.float32), np.asarray(high, np.float32))
        return self._bounds

    def fresh_copy(self) -> Any:
        """A fresh env like ``gym_env`` (for samples that must not disturb it)."""
        if self._make_copy is not None:
            return self._make_copy()
        try:
            return copy.deepcopy(self.gym_env)
        except Exception:  # an env holding e.g. a window or a socket: sample it in place
            return self.gym_env

    def gym_actions(self, values: np.ndarray) -> np.ndarray:
        """HEDGER action values (..., 1) -> what the env's ``step`` takes: int64 (...) for
        ``Discrete`` (``start + i``), float32 (..., 1) for a Box (clipped to its bounds)."""
        values = np.asarray(values)
        if self.action_space.is_discrete:
            return np.rint(values[..., 0]).astype(np.int64) + self.action_start
        low, high = self.action_space.low[0], self.action_space.high[0]
        return np.clip(values, low, high).astype(np.float32)

    def gym_action(self, value: np.ndarray) -> Any:
        """One action value (1,) -> one env action (a Python int, or float32 (1,))."""
        a = self.gym_actions(value)
        return int(a) if self.action_space.is_discrete else a


class ResolvedEnv(NamedTuple):
    """What ``resolve_env`` returns. env: functional env or ``GymnasiumEnv``; name: the
    preset key (``envs.make`` name, or the Gymnasium id); env_id: what ``save`` stores to
    rebuild it (None: nothing to rebuild from); params: the env params to use by default
    (None: ``env.default_params()``); from_instance: built from a user's env instance."""

    env: Any
    name: Optional[str]
    env_id: Optional[str]
    params: Any
    from_instance: bool


def _is_gym_env(obj: Any) -> bool:
    import sys

    gymnasium = sys.modules.get("gymnasium")   # not imported: cannot be one of its envs
    return gymnasium is not None and isinstance(obj, gymnasium.Env)


def _gym_make(env_id: str, env_kwargs: Dict[str, Any]) -> Any:
    import gymnasium

    import envs.gym_adapter  # noqa: F401  (registers the project's ids)

    try:
        return gymnasium.make(env_id, **env_kwargs)
    except gymnasium.error.Error as exc:
        raise ValueError(f"unknown environment {env_id!r}: not a registered Gymnasium id nor "
                         f"an envs.make name ({exc})") from None


def resolve_env(env: Any, env_kwargs: Optional[Dict[str, Any]] = None) -> ResolvedEnv:
    """Decide how ``Hedger`` runs ``env`` (see the module doc).

    env: an id/name string, a ``gymnasium.Env`` or a functional env object. env_kwargs:
    keyword arguments for ``envs.make`` / ``gymnasium.make`` (a string env only).
    Raises ``ValueError`` for an unknown id or an unsupported space.
    """
    env_kwargs = dict(env_kwargs or {})
    if isinstance(env, str):
        if is_functional_name(env):
            fenv, name = make_env(env, **env_kwargs)
            return ResolvedEnv(fenv, name, env, None, False)
        gym_env = _gym_make(env, env_kwargs)
        host = GymnasiumEnv(gym_env, env_id=env,
                            make_copy=lambda: _make_by_id(env, env_kwargs))
        return ResolvedEnv(host, env, env, None, False)
    if env_kwargs:
        raise ValueError("env_kwargs: only used when env is an id/name")
    if _is_gym_env(env):
        from envs.gym_adapter import FunctionalGymEnv

        spec_id = getattr(getattr(env, "spec", None), "id", None)
        inner = env.unwrapped
        if isinstance(inner, FunctionalGymEnv):
            name = getattr(inner.env, "name", None)
            env_id = spec_id if spec_id in GYM_IDS else name
            return ResolvedEnv(inner.env, name, env_id, inner.params, True)
        host = GymnasiumEnv(env, env_id=spec_id)
        return ResolvedEnv(host, host.name, spec_id, None, True)
    name = getattr(env, "name", None)
    return ResolvedEnv(env, name, name, None, True)


def _make_by_id(env_id: str, env_kwargs: Dict[str, Any]) -> Any:
    """A fresh copy of an env made by id: ``gymnasium.make(env_id, **env_kwargs)``."""
    import gymnasium

    return gymnasium.make(env_id, **env_kwargs)
