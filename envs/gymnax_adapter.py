"""gymnax adapter: a gymnax environment as a functional env of ``envs.base``.

An optional extra (``pip install hedger-jax[gymnax]``); this module imports gymnax only to
make an env from its id. Any object with gymnax's API works: ``reset_env(key, params) ->
(obs, state)``, ``step_env(key, state, action, params) -> (obs, state, reward, done, info)``
(no auto-reset), ``default_params`` (a property), ``observation_space(params)`` and
``action_space(params)`` (gymnax spaces: ``Discrete`` with ``n``, ``Box`` with ``low``,
``high``, ``shape``), a ``time`` step counter in the state and ``max_steps_in_episode`` in
the params.

``GymnaxEnv`` maps it onto the project's interface, so ``make_train`` runs jitted and vmapped
over seeds on gymnax's tasks::

    env = GymnaxEnv("Acrobot-v1")
    config = HedgerConfig.for_env(env, bandwidth=0.25, gamma=0.99)
    train = make_train(env, config, RunConfig(...)).train
    jax.jit(jax.vmap(train))(jax.random.split(key, n_seeds))

* ``reset(key, params)`` is gymnax's ``reset_env(key, params)``.
* ``step(key, state, action, params)`` is ``step_env`` without gymnax's auto-reset. It feeds
  ``step_env`` the first half of ``jax.random.split(key)``, as gymnax's own ``step`` does, so
  the same keys give gymnax's own trajectory.
* ``terminated`` vs ``truncated``: gymnax releases before 1.0 fold the time limit into
  ``step_env``'s ``done``; from 1.0 ``done`` is the natural terminal only and the time limit
  is ``is_truncated``. Either way ``truncated = state.time >= params.max_steps_in_episode``
  (the step counter after the step) and not ``terminated``. With a folded ``done``
  (``folds_time_limit``, default: the env has no ``is_truncated``), ``terminated = done``
  and not ``truncated``: a natural terminal on the very step of the time limit is then
  reported as a truncation (the fold has lost the difference).
* Actions. ``Discrete(n)``: the action values (0,), (1,), ..., (n-1,) (gymnax's indices,
  passed to ``step_env`` as int32). ``Box`` of shape (1,): the interval [low, high], passed
  as float32 (1,) (gymnax clips it). Other spaces raise ``ValueError``.
* ``obs_bounds(params)``: gymnax's ``observation_space(params)`` bounds; a dimension whose
  bound is unbounded (±inf, or a magnitude of at least 1e6, as CartPole's float32 max) takes
  its range from 2,000 random-action steps with ``PRNGKey(SAMPLE_SEED)`` (``envs.scaling``:
  min/max widened by 10 % per side, a constant dimension a unit range).
* ``max_steps``: ``max_steps_in_episode`` of the params given at construction (default
  gymnax's default params): static, the length of the agent's episode buffers.
* ``evaluation_starts(key, params, n)``: n independent ``reset_env`` starts.
* ``render_rgb`` raises ``NotImplementedError``.
* Evaluation (``agent.evaluate``) counts an episode that *terminated* as a success; for tasks
  whose termination is a failure (CartPole) read its ``mean_steps`` accordingly.
"""
from __future__ import annotations

from typing import Any, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from envs import scaling
from envs.spaces import ActionSpace

__all__ = ["GymnaxEnv"]


def _canonical(tree: Any) -> Any:
    """Every leaf a strongly typed JAX array (gymnax keeps e.g. ``time = 0`` as a Python
    int, and some leaves weakly typed only in reset), so that reset and step states have the
    same types in a loop carry."""
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.asarray(x).dtype), tree)


def _action_space(space: Any) -> ActionSpace:
    """A gymnax action space -> ``ActionSpace`` (discrete indices, or a (1,) box)."""
    if hasattr(space, "n") and tuple(getattr(space, "shape", ())) == ():
        return ActionSpace.discrete(np.arange(int(space.n), dtype=np.float64))
    shape = tuple(getattr(space, "shape", (None,)) or ())
    if hasattr(space, "low") and hasattr(space, "high") and shape in ((1,), ()):
        low = np.asarray(space.low, np.float64).reshape(-1)[0]
        high = np.asarray(space.high, np.float64).reshape(-1)[0]
        if np.isfinite(low) and np.isfinite(high):
            return ActionSpace.box(low, high)
    raise ValueError(f"unsupported gymnax action space {space!r}: HEDGER supports Discrete or "
                     "a one-dimensional Box (shape (1,)) with finite bounds")


class GymnaxEnv:
    """A gymnax environment behind the functional interface of ``envs.base`` (module doc).

    Args:
      env: a gymnax id (``"MountainCar-v0"``, ``"Acrobot-v1"``, ``"CartPole-v1"``,
        ``"Pendulum-v1"``, ...; made with ``gymnax.make``) or an environment instance.
      params: its params (default: ``gymnax.make``'s, or ``env.default_params``).
      folds_time_limit: whether ``step_env``'s ``done`` includes the time limit (None: when
        the env has no ``is_truncated``, i.e. gymnax < 1.0).

    Attributes: ``gymnax_env``, ``env_id``, ``name`` (``"gymnax/<id>"``), ``obs_dim``,
    ``action_dim``, ``action_space``, ``max_steps``, ``folds_time_limit``.
    """

    render_fps = 30

    def __init__(self, env: Any, params: Any = None, *,
                 folds_time_limit: Optional[bool] = None):
        if isinstance(env, str):
            import gymnax

            gx, made_params = gymnax.make(env)
            self.env_id = env
            params = made_params if params is None else params
            self._key = (type(gx), env)
        else:
            gx = env
            self.env_id = str(getattr(env, "name", type(env).__name__))
            self._key = (id(gx),)
        self.gymnax_env = gx
        self._params = gx.default_params if params is None else params
        if folds_time_limit is None:
            folds_time_limit = not hasattr(gx, "is_truncated")
        self.folds_time_limit = bool(folds_time_limit)
        self.name = f"gymnax/{self.env_id}"
        box = gx.observation_space(self._params)
        if len(tuple(box.shape)) != 1:
            raise ValueError(f"unsupported gymnax observation space {box!r}: HEDGER supports "
                             "a Box of shape (S,)")
        self.obs_dim = int(box.shape[0])
        self.action_space = _action_space(gx.action_space(self._params))
        self.action_dim = self.action_space.action_dim
        self.max_steps = int(np.asarray(self._params.max_steps_in_episode))
        low, high = self._declared_bounds(self._params)
        self._needs_samples = bool(np.any(np.asarray(scaling.unbounded(low, high))))
        self._key = self._key + (self.max_steps, self.folds_time_limit)

    # Hashable by value (same id, same settings), so that equal envs share compiled code.
    def __eq__(self, other) -> bool:
        return isinstance(other, GymnaxEnv) and self._key == other._key

    def __hash__(self) -> int:
        return hash((GymnaxEnv,) + self._key)

    def __repr__(self) -> str:
        return f"GymnaxEnv({self.env_id!r}, max_steps={self.max_steps})"

    def default_params(self) -> Any:
        return self._params

    # -- resets -----------------------------------------------------------------------------
    def reset(self, key: jax.Array, params: Any) -> Tuple[jax.Array, Any]:
        """gymnax's ``reset_env`` -> (obs float32 (obs_dim,), state)."""
        obs, state = self.gymnax_env.reset_env(key, params)
        return jnp.asarray(obs, jnp.float32).reshape((self.obs_dim,)), _canonical(state)

    def evaluation_starts(self, key: jax.Array, params: Any, n: int):
        """n independent starts -> (obs float32 (n, obs_dim), states with leading axis n)."""
        return jax.vmap(self.reset, in_axes=(0, None))(jax.random.split(key, n), params)

    # -- dynamics ---------------------------------------------------------------------------
    def _gymnax_action(self, action: jax.Array) -> jax.Array:
        """Action value (1,) -> gymnax's action: an int32 index () or float32 (1,)."""
        a = jnp.reshape(jnp.asarray(action, jnp.float32), (self.action_dim,))
        if self.action_space.is_discrete:
            n = self.action_space.n_actions
            return jnp.clip(jnp.round(a[0]), 0, n - 1).astype(jnp.int32)
        return a

    def step(self, key: jax.Array, state: Any, action: jax.Array, params: Any):
        """``step_env`` without auto-reset (module doc) -> (obs float32 (obs_dim,), state,
        reward float32 (), terminated bool (), truncated bool (), info dict)."""
        key_step, _ = jax.random.split(key)
        obs, state, reward, done, info = self.gymnax_env.step_env(
            key_step, state, self._gymnax_action(action), params)
        limit = jnp.asarray(state.time >= params.max_steps_in_episode, bool)
        done = jnp.asarray(done, bool).reshape(())
        terminated = done & ~limit if self.folds_time_limit else done
        truncated = limit & ~terminated
        return (jnp.asarray(obs, jnp.float32).reshape((self.obs_dim,)), _canonical(state),
                jnp.asarray(reward, jnp.float32).reshape(()), terminated, truncated,
                dict(info) if isinstance(info, dict) else {})

    # -- scaling ----------------------------------------------------------------------------
    def _declared_bounds(self, params: Any):
        box = self.gymnax_env.observation_space(params)
        low = jnp.broadcast_to(jnp.asarray(box.low, jnp.float32), (self.obs_dim,))
        high = jnp.broadcast_to(jnp.asarray(box.high, jnp.float32), (self.obs_dim,))
        return low, high

    def random_observations(self, params: Any, n: int = scaling.SAMPLE_STEPS,
                            seed: int = scaling.SAMPLE_SEED) -> jax.Array:
        """The observation each of n uniformly random-action steps acts from (episodes
        restart when they end), keyed by ``PRNGKey(seed)`` -> float32 (n, obs_dim)."""
        space = self.action_space
        low = jnp.asarray(space.low, jnp.float32)
        high = jnp.asarray(space.high, jnp.float32)

        def body(carry, key):
            obs, state = carry
            k_act, k_step, k_reset = jax.random.split(key, 3)
            if space.is_discrete:
                a = jax.random.randint(k_act, (1,), 0, space.n_actions).astype(jnp.float32)
            else:
                a = jax.random.uniform(k_act, (self.action_dim,), jnp.float32, low, high)
            nobs, nstate, _, te, tr, _ = self.step(k_step, state, a, params)
            robs, rstate = self.reset(k_reset, params)
            done = te | tr
            carry = jax.tree_util.tree_map(lambda r, s: jnp.where(done, r, s),
                                           (robs, rstate), (nobs, nstate))
            return carry, obs

        k0, k_run = jax.random.split(jax.random.PRNGKey(seed))
        _, obs = jax.lax.scan(body, self.reset(k0, params), jax.random.split(k_run, n))
        return obs

    def obs_bounds(self, params: Any) -> Tuple[jax.Array, jax.Array]:
        """Scaling range (module doc) -> (low, high) float32 (obs_dim,) each. Jittable.
        Which dimensions are unbounded is decided once, from the construction params."""
        low, high = self._declared_bounds(params)
        if not self._needs_samples:
            return low, high
        return scaling.scaling_bounds(low, high, self.random_observations(params))

    def render_rgb(self, state: Any, params: Any = None):
        raise NotImplementedError(f"{self.name}: no renderer (use gymnax's own visualiser)")
