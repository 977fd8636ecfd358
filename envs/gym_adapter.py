"""Gymnasium adapter: any functional env of ``envs.base`` as a ``gymnasium.Env``.

``FunctionalGymEnv`` holds one environment instance on the host: the functional ``state``
pytree, a JAX PRNG key and a step counter. ``reset``/``step`` call the functional env's pure
``reset``/``step`` through functions jitted once per adapter instance (the ``params`` pytree
is an argument, so changing its values never recompiles).

Key path (so that a Gymnasium rollout is reproducible with the functional API)::

    reset(seed=s):   key = jax.random.PRNGKey(s)              # raw uint32 (2,) key
                     key, k = jax.random.split(key)
                     obs, state = env.reset(k, params)         # or env.reset_to(k, params, start)
    step(a):         key, k = jax.random.split(key)
                     obs, state, r, term, trunc, info = env.step(k, state, value(a), params)

``reset()`` without a seed continues the same key chain (the first unseeded reset draws the key
from Gymnasium's ``np_random``).

Spaces:
  * ``action_space``: ``Discrete(n)`` for a discrete ``ActionSpace`` (index ``i`` -> the action
    value ``ActionSpace.values[i]``, see ``action_value``), ``Box(low, high, (action_dim,))``
    for a continuous one (the action is passed to the functional env as is; the env clips).
  * ``observation_space``: ``Box(low, high, (obs_dim,), float32)``. By default the env's
    ``obs_space_bounds(params)`` when it has one (hard bounds that contain every observation it
    can emit), else ``obs_bounds(params)`` (the scaling range; correct for envs that clip their
    observations to it, like mountain car). Pass ``obs_space_bounds=(low, high)`` or
    ``"unbounded"`` (±inf) to override. ``HedgerCorridor-v0`` is registered with
    ``"hard_or_unbounded"``: its laser-derived observation can leave the nominal scaling range
    (angle beyond ±pi/4, offset beyond ±width/2, and with the geometric observation the distance
    beyond ``length``), so it uses the env's hard bounds (``Corridor.obs_space_bounds``: finite
    for the laser observation, the distance unbounded for the geometric one), else ±inf.

Time limit: by default the functional env's own ``truncated`` flag is used (it truncates at
``env.max_steps``). ``time_limit=N`` replaces it by the adapter's own step counter
(``truncated = steps >= N``; the functional env's flag is then ignored), e.g. for long,
uncapped keyboard demonstrations. The registered ids carry ``max_episode_steps = env.max_steps``,
so ``gymnasium.make`` adds a ``TimeLimit`` that fires at the same step as the env's own flag
(no change of semantics: terminated always wins for bootstrapping). To lengthen episodes through
``gymnasium.make`` pass both: ``gymnasium.make(id, time_limit=2000, max_episode_steps=2000)``
(``max_episode_steps`` alone would still be cut at ``env.max_steps`` by the env itself).

Render modes: ``"rgb_array"`` returns the env's ``render_rgb(state, params)`` (uint8 (H, W, 3));
``"human"`` shows the same frame in a pygame window (needs a display, or
``SDL_VIDEODRIVER=dummy`` for an invisible one).

Registered ids (``register_envs()``, run on import of this module, idempotent):
``HedgerMountainCar-v0`` (discrete {-1, 0, +1}), ``HedgerMountainCarContinuous-v0``,
``HedgerCorridor-v0``.
"""
from __future__ import annotations

from typing import Any, Optional, Tuple, Union

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces

from envs.base import FunctionalEnv

__all__ = ["FunctionalGymEnv", "register_envs", "REGISTERED_IDS"]

#: Gymnasium id -> ``envs.make`` name.
REGISTERED_IDS = {
    "HedgerMountainCar-v0": "mountain_car_discrete",
    "HedgerMountainCarContinuous-v0": "mountain_car_continuous",
    "HedgerCorridor-v0": "corridor",
}
#: Extra constructor kwargs per id (mountain car clips its observation to ``obs_bounds``).
_REGISTER_KWARGS = {
    "HedgerCorridor-v0": {"obs_space_bounds": "hard_or_unbounded"},
}


def _to_numpy_tree(tree: Any) -> Any:
    return jax.tree_util.tree_map(lambda x: np.asarray(x), tree)


class FunctionalGymEnv(gymnasium.Env):
    """A functional env (``envs.base``) behind the Gymnasium API.

    Args:
      env: a functional env instance, or a name for ``envs.make`` (e.g. ``"corridor"``).
      params: the env's params pytree; default ``env.default_params()``.
      render_mode: ``None``, ``"rgb_array"`` or ``"human"``.
      time_limit: ``None`` (use the env's own truncation at ``env.max_steps``) or an int: the
        adapter truncates after that many steps and ignores the env's own flag.
      reset_options: default ``options`` for ``reset`` (e.g. ``{"start": start}``), used when
        ``reset`` is called without options.
      obs_space_bounds: ``None`` (see module doc), ``"unbounded"`` (±inf),
        ``"hard_or_unbounded"`` (the env's ``obs_space_bounds(params)`` if it has one, else
        ±inf) or ``(low, high)``.
      env_kwargs: extra keyword arguments for ``envs.make`` when ``env`` is a name.

    Observations are float32 numpy arrays of shape (obs_dim,); rewards Python floats;
    ``info`` is the env's info pytree converted to numpy (plus nothing else).
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 30, "jax": True}

    def __init__(
        self,
        env: Union[FunctionalEnv, str],
        params: Any = None,
        render_mode: Optional[str] = None,
        time_limit: Optional[int] = None,
        reset_options: Optional[dict] = None,
        obs_space_bounds: Union[None, str, Tuple[Any, Any]] = None,
        env_kwargs: Optional[dict] = None,
    ):
        if isinstance(env, str):
            import envs as _envs

            env = _envs.make(env, **(env_kwargs or {}))
        self.env = env
        self.params = env.default_params() if params is None else params
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']}, "
                             f"got {render_mode!r}")
        self.render_mode = render_mode
        if time_limit is not None and int(time_limit) < 1:
            raise ValueError(f"time_limit must be >= 1, got {time_limit}")
        self.time_limit = None if time_limit is None else int(time_limit)
        self.reset_options = dict(reset_options) if reset_options else {}
        self.metadata = dict(self.metadata)
        self.metadata["render_fps"] = int(getattr(env, "render_fps", 30))

        # ---- spaces --------------------------------------------------------------------
        aspace = env.action_space
        self.action_dim = aspace.action_dim
        if aspace.is_discrete:
            self._action_values = aspace.values_array()  # (n_actions, action_dim)
            self.action_space = spaces.Discrete(aspace.n_actions)
        else:
            self._action_values = None
            self.action_space = spaces.Box(np.asarray(aspace.low, np.float32),
                                           np.asarray(aspace.high, np.float32),
                                           (self.action_dim,), np.float32)
        self.obs_dim = int(env.obs_dim)
        hard = getattr(env, "obs_space_bounds", None)
        if obs_space_bounds is None or (obs_space_bounds == "hard_or_unbounded"
                                        and hard is not None):
            low, high = (hard or env.obs_bounds)(self.params)
        elif isinstance(obs_space_bounds, str):
            if obs_space_bounds not in ("unbounded", "hard_or_unbounded"):
                raise ValueError(f"obs_space_bounds: unknown {obs_space_bounds!r}")
            low = np.full((self.obs_dim,), -np.inf, np.float32)
            high = np.full((self.obs_dim,), np.inf, np.float32)
        else:
            low, high = obs_space_bounds
        low = np.broadcast_to(np.asarray(low, np.float32), (self.obs_dim,)).copy()
        high = np.broadcast_to(np.asarray(high, np.float32), (self.obs_dim,)).copy()
        self.observation_space = spaces.Box(low, high, (self.obs_dim,), np.float32)

        # ---- jitted functional calls (compiled once per instance) ----------------------
        fenv = env

        def _reset(key, params):
            key, sub = jax.random.split(key)
            obs, state = fenv.reset(sub, params)
            return key, obs, state

        def _step(key, state, action, params):
            key, sub = jax.random.split(key)
            obs, state, reward, terminated, truncated, info = fenv.step(sub, state, action, params)
            return key, obs, state, reward, terminated, truncated, info

        self._reset_fn = jax.jit(_reset)
        self._step_fn = jax.jit(_step)
        if hasattr(env, "reset_to"):
            def _reset_to(key, params, start):
                key, sub = jax.random.split(key)
                obs, state = fenv.reset_to(sub, params, start)
                return key, obs, state

            self._reset_to_fn = jax.jit(_reset_to)
        else:
            self._reset_to_fn = None

        self._key: Optional[jax.Array] = None
        self._state: Any = None
        self._elapsed = 0
        self._window = None
        self._clock = None

    # ------------------------------------------------------------------------------------
    @property
    def state(self) -> Any:
        """The functional env's current state pytree (None before the first reset)."""
        return self._state

    @property
    def elapsed_steps(self) -> int:
        """Steps taken since the last reset."""
        return self._elapsed

    def action_value(self, action: Any) -> np.ndarray:
        """Gymnasium action -> the functional env's action value, float32 (action_dim,).

        Discrete: ``action`` is an index into ``ActionSpace.values``. Continuous: the vector
        itself (reshaped to (action_dim,)).
        """
        if self._action_values is not None:
            idx = int(np.asarray(action).reshape(()))
            if not 0 <= idx < len(self._action_values):
                raise ValueError(f"discrete action index {idx} out of range "
                                 f"[0, {len(self._action_values)})")
            return self._action_values[idx]
        return np.asarray(action, np.float32).reshape((self.action_dim,))

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        """Start an episode. ``options={"start": s}`` starts from a given physical state through
        the env's ``reset_to`` (format of ``s``: see the env); default options from the
        constructor's ``reset_options``. Returns (obs float32 (obs_dim,), info dict)."""
        super().reset(seed=seed)
        if seed is not None:
            self._key = jax.random.PRNGKey(seed)
        elif self._key is None:
            self._key = jax.random.PRNGKey(int(self.np_random.integers(0, 2**31 - 1)))
        opts = self.reset_options if options is None else options
        start = opts.get("start") if opts else None
        if start is not None:
            if self._reset_to_fn is None:
                raise ValueError(f"{type(self.env).__name__} has no reset_to: cannot use "
                                 "options['start']")
            if isinstance(start, (list, tuple, np.ndarray, float, int)):
                start = jnp.asarray(start, jnp.float32)  # else: a pytree (e.g. an env state)
            self._key, obs, self._state = self._reset_to_fn(self._key, self.params, start)
        else:
            self._key, obs, self._state = self._reset_fn(self._key, self.params)
        self._elapsed = 0
        if self.render_mode == "human":
            self.render()
        return np.asarray(obs, np.float32), {}

    def step(self, action: Any):
        """One step. Returns (obs float32 (obs_dim,), reward float, terminated bool,
        truncated bool, info dict of numpy arrays)."""
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        value = jnp.asarray(self.action_value(action), jnp.float32)
        (self._key, obs, self._state, reward, terminated, truncated,
         info) = self._step_fn(self._key, self._state, value, self.params)
        self._elapsed += 1
        terminated = bool(terminated)
        if self.time_limit is None:
            truncated = bool(truncated)
        else:
            truncated = self._elapsed >= self.time_limit
        info = _to_numpy_tree(info)
        if not isinstance(info, dict):
            info = {"env_info": info}
        if self.render_mode == "human":
            self.render()
        return np.asarray(obs, np.float32), float(reward), terminated, truncated, info

    def render(self):
        """``"rgb_array"``: uint8 (H, W, 3) of the current state. ``"human"``: draw it in a
        pygame window (returns None). ``None`` render mode: returns None (with a warning)."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without a render_mode; pass "
                                  "render_mode='rgb_array' or 'human' to the constructor")
            return None
        if self._state is None:
            return None
        frame = np.asarray(self.env.render_rgb(self._state, self.params), dtype=np.uint8)
        if self.render_mode == "rgb_array":
            return frame
        self._render_human(frame)
        return None

    def _render_human(self, frame: np.ndarray) -> None:
        import pygame  # optional dependency, only for the human render mode

        if self._window is None:
            pygame.display.init()
            self._window = pygame.display.set_mode((frame.shape[1], frame.shape[0]))
            pygame.display.set_caption(getattr(self.env, "name", type(self.env).__name__))
            self._clock = pygame.time.Clock()
        surf = pygame.surfarray.make_surface(np.ascontiguousarray(frame.swapaxes(0, 1)))
        self._window.blit(surf, (0, 0))
        pygame.event.pump()
        pygame.display.flip()
        self._clock.tick(self.metadata["render_fps"])

    def close(self):
        if self._window is not None:
            import pygame

            pygame.display.quit()
            pygame.quit()
            self._window = None
        super().close()


def register_envs() -> list:
    """Register the Gymnasium ids in ``REGISTERED_IDS`` (idempotent).

    Each id's ``max_episode_steps`` is the functional env's ``max_steps``. An id whose env
    module cannot be imported is skipped. Returns the ids now registered.
    """
    import envs as _envs

    done = []
    for gym_id, name in REGISTERED_IDS.items():
        if gym_id in gymnasium.registry:
            done.append(gym_id)
            continue
        try:
            max_steps = int(_envs.make(name).max_steps)
        except ModuleNotFoundError as e:  # the env's own module is not available
            if not (e.name or "").startswith("envs."):
                raise
            continue
        gymnasium.register(
            id=gym_id,
            entry_point="envs.gym_adapter:FunctionalGymEnv",
            max_episode_steps=max_steps,
            kwargs={"env": name, **_REGISTER_KWARGS.get(gym_id, {})},
        )
        done.append(gym_id)
    return done


register_envs()
