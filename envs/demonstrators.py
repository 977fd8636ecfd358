"""Example policies in control (HEDGER's phase 1) and an episode recorder for any env.

* :class:`Policy` — a jittable policy is a pair of pure functions::

      init(key) -> pstate
      act(key, obs, pstate) -> (action float32 (action_dim,), pstate)

  ``pstate`` is any pytree (a memory for delays, a held key, ...). Policies must be hashable
  (they are static arguments of the jitted recorder): build them once and reuse them.

* :func:`record_episodes` runs ``n_episodes`` episodes of a policy in an env (vmapped over
  episodes, ``lax.scan`` over ``max_steps`` with a done mask) and returns
  :class:`envs.demonstrations.Demonstrations`.

* A *simulated person* driving the mountain car from the bottom of the hill with the discrete
  keys {-1, 0, +1}: :func:`simulated_person_policy`, :func:`simulated_person_demonstrations`.
  It stands in for the paper's 11 keyboard runs by 3 people (mean 210 steps, best 106).
"""
from __future__ import annotations

import functools
from typing import Any, Callable, NamedTuple, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from envs.demonstrations import Demonstrations

__all__ = ["Policy", "record_episodes", "PersonParams", "PERSONS", "simulated_person_policy",
           "simulated_person_demonstrations", "energy_pumping_policy", "random_policy"]


class Policy(NamedTuple):
    """A jittable policy: ``init(key) -> pstate``, ``act(key, obs, pstate) -> (action, pstate)``."""
    init: Callable[[jax.Array], Any]
    act: Callable[[jax.Array, jax.Array, Any], Tuple[jax.Array, Any]]


# ------------------------------------------------------------------------------------------
# Recorder
# ------------------------------------------------------------------------------------------
@functools.partial(jax.jit, static_argnames=("env", "act", "max_steps", "batched_start"))
def _record(env, params, act, pstate0, reset_keys, run_keys, max_steps: int, start,
            batched_start: bool):
    """Jitted core: vmapped episodes. Only ``act`` (not ``init``) is static, so policies
    sharing an ``act`` share compiled code. Leading axis E on pstate0/keys (/start)."""
    action_dim = env.action_space.action_dim

    def one_episode(k_reset, k_run, pstate, start_i):
        if start_i is None:
            obs, state = env.reset(k_reset, params)
        else:
            obs, state = env.reset_to(k_reset, params, start_i)

        def body(carry, xs):
            obs, state, pstate, done = carry
            t, ka, ks = xs
            action, pstate2 = act(ka, obs, pstate)
            action = jnp.reshape(jnp.asarray(action, jnp.float32), (action_dim,))
            next_obs, state2, reward, term, _env_trunc, _ = env.step(ks, state, action, params)
            valid = jnp.logical_not(done)
            term = term & valid
            trunc = (t == max_steps - 1) & valid & jnp.logical_not(term)
            out = dict(obs=obs, action=action, reward=jnp.asarray(reward, jnp.float32),
                       next_obs=next_obs, terminated=term, truncated=trunc, valid=valid)
            out = {k: jnp.where(valid, v, jnp.zeros_like(v)) for k, v in out.items()}
            keep = lambda new, old: jnp.where(done, old, new)
            state2 = jax.tree_util.tree_map(keep, state2, state)
            pstate2 = jax.tree_util.tree_map(keep, pstate2, pstate)
            next_obs = keep(next_obs, obs)
            return (next_obs, state2, pstate2, done | term | trunc), out

        # Per-step keys drawn up front (cheaper to compile than splitting inside the scan).
        step_keys = jax.random.split(k_run, (max_steps, 2))
        carry = (obs, state, pstate, jnp.zeros((), bool))
        _, out = jax.lax.scan(body, carry, (jnp.arange(max_steps), step_keys[:, 0],
                                            step_keys[:, 1]))
        return out

    if start is None:
        return jax.vmap(lambda a, b, c: one_episode(a, b, c, None))(reset_keys, run_keys, pstate0)
    return jax.vmap(one_episode, in_axes=(0, 0, 0, 0 if batched_start else None))(
        reset_keys, run_keys, pstate0, start)


def _episode_keys(ep_keys):
    """(E,) episode keys -> (reset, policy-init, run) keys, each (E,)."""
    sub = jax.vmap(lambda k: jax.random.split(k, 3))(ep_keys)
    return sub[:, 0], sub[:, 1], sub[:, 2]


def _run_recorder(env, params, act, pstate0, reset_keys, run_keys, max_steps, start,
                  source) -> Demonstrations:
    n_episodes, max_steps = int(reset_keys.shape[0]), int(max_steps)
    if n_episodes < 1 or max_steps < 1:
        raise ValueError("record_episodes: n_episodes and max_steps must be >= 1")
    batched = False
    if start is not None:
        start = jnp.asarray(start, jnp.float32)
        batched = start.ndim >= 2
        if batched and start.shape[0] != n_episodes:
            raise ValueError(f"record_episodes: batched start has leading axis {start.shape[0]}, "
                             f"expected n_episodes={n_episodes}")
    out = _record(env, params, act, pstate0, reset_keys, run_keys, max_steps, start, batched)
    out = {k: np.asarray(v) for k, v in jax.device_get(out).items()}
    T = max(int(out["valid"].sum(axis=1).max()), 1)
    out = {k: v[:, :T] for k, v in out.items()}
    return Demonstrations(**out, env_id=env.name, source=source)


def record_episodes(env, params, policy: Policy, key: jax.Array, n_episodes: int,
                    max_steps: int, start=None, source: str = "policy") -> Demonstrations:
    """Run ``n_episodes`` episodes of ``policy`` in ``env`` and record them.

    Args:
      env: a functional env (``envs.base``); hashable (a static jit argument).
      params: its params pytree.
      policy: a :class:`Policy`; ``policy.act`` must be hashable (reuse the same function to
        avoid recompiling); ``policy.init`` runs outside the jitted scan.
      key: PRNG key; episode ``i`` uses ``split(key, n_episodes)[i]``, split again into its
        reset, policy-init and per-step keys.
      n_episodes: E.
      max_steps: the recorder's time limit, which *replaces* the env's own (``env.max_steps``
        is ignored: demonstrations may be longer). The step at index ``max_steps - 1`` of an
        episode still running is reported ``truncated`` (never ``terminated``).
      start: ``None`` for ``env.reset`` (fresh random starts), else a start for
        ``env.reset_to``: one start (e.g. shape (2,) for mountain car) for every episode, or a
        batch with leading axis ``n_episodes`` (any array with ``ndim >= 2``).
      source: stored in the result's ``source``.

    Returns:
      Demonstrations with numpy arrays of shape (E, T, ...), T = the longest episode's length;
      padding steps are zero with ``valid`` False.
    """
    n_episodes = int(n_episodes)
    if n_episodes < 1:
        raise ValueError("record_episodes: n_episodes must be >= 1")
    reset_keys, init_keys, run_keys = _episode_keys(jax.random.split(key, n_episodes))
    pstate0 = jax.vmap(policy.init)(init_keys)
    return _run_recorder(env, params, policy.act, pstate0, reset_keys, run_keys, max_steps,
                         start, source)


# ------------------------------------------------------------------------------------------
# Simple policies
# ------------------------------------------------------------------------------------------
def _stateless(fn) -> Policy:
    return Policy(init=lambda key: jnp.zeros((), jnp.int32),
                  act=lambda key, obs, ps: (fn(key, obs), ps))


@functools.lru_cache(maxsize=None)
def energy_pumping_policy() -> Policy:
    """Mountain car: push in the direction of the velocity (right at v = 0). Deterministic."""
    return _stateless(lambda key, obs: jnp.where(obs[1] >= 0, 1.0, -1.0)[None].astype(jnp.float32))


@functools.lru_cache(maxsize=None)
def random_policy(values: Tuple[float, ...] = (-1.0, 0.0, 1.0)) -> Policy:
    """Uniformly random choice among scalar action ``values`` (shape (1,) actions)."""
    vals = jnp.asarray(values, jnp.float32)
    return _stateless(lambda key, obs: jax.random.choice(key, vals)[None])


# ------------------------------------------------------------------------------------------
# The simulated person at the keyboard (mountain car, discrete keys)
# ------------------------------------------------------------------------------------------
class PersonParams(NamedTuple):
    """How one simulated person drives (all per person; per-run values are drawn at ``init``).

    The person watches the car with a reaction delay (``delay_lo..delay_hi`` steps, drawn per
    run), anticipates the turn-around by ``lead`` steps (extrapolating the velocity they saw,
    drawn uniformly in ``lead_lo..lead_hi`` per run; anticipating is what beats naive
    "push with the velocity", 124 steps, towards the optimum of 102), and holds the key in the
    direction of the anticipated velocity. They start with the right key, except with
    probability ``p_left_first``. At each intended key change they hesitate (release all keys)
    with probability ``p_hesitate`` for 1..``hesitate_max`` steps, or press the wrong key with
    probability ``p_wrong`` for 1..``wrong_max`` steps; at any other step they coast (release)
    with probability ``p_coast`` for 1..``coast_max`` steps.
    """
    delay_lo: int
    delay_hi: int
    lead_lo: float
    lead_hi: float
    p_left_first: float
    p_hesitate: float
    hesitate_max: int
    p_wrong: float
    wrong_max: int
    p_coast: float
    coast_max: int


#: Three people: a practised one, an average one, a novice.
PERSONS: Tuple[PersonParams, ...] = (
    PersonParams(delay_lo=2, delay_hi=4, lead_lo=14.0, lead_hi=24.0, p_left_first=0.0,
                 p_hesitate=0.1, hesitate_max=3, p_wrong=0.0, wrong_max=2,
                 p_coast=0.003, coast_max=4),
    PersonParams(delay_lo=5, delay_hi=11, lead_lo=0.0, lead_hi=9.0, p_left_first=0.35,
                 p_hesitate=0.5, hesitate_max=12, p_wrong=0.15, wrong_max=8,
                 p_coast=0.07, coast_max=15),
    PersonParams(delay_lo=8, delay_hi=14, lead_lo=0.0, lead_hi=4.0, p_left_first=0.5,
                 p_hesitate=0.6, hesitate_max=16, p_wrong=0.2, wrong_max=10,
                 p_coast=0.1, coast_max=18),
)

_BUF = 1 + max(p.delay_hi for p in PERSONS) + 2  # observation memory (steps)


class _PersonState(NamedTuple):
    buf: jax.Array        # float32 (_BUF, 2): obs history, buf[0] = the newest
    t: jax.Array          # int32 (): steps taken
    delay: jax.Array      # int32 (): this run's reaction delay
    lead: jax.Array       # float32 (): this run's anticipation (steps)
    intent: jax.Array     # float32 (): the key the person means to hold (-1 or +1)
    override: jax.Array   # float32 (): key pressed during a hesitation / slip (0 or -intent)
    count: jax.Array      # int32 (): steps left of the override
    # The person's habits (float32 scalars; traced, so one compiled ``act`` serves everyone):
    p_hesitate: jax.Array
    hesitate_max: jax.Array
    p_wrong: jax.Array
    wrong_max: jax.Array
    p_coast: jax.Array
    coast_max: jax.Array


def _person_init(p: PersonParams, key) -> _PersonState:
    f = lambda x: jnp.asarray(x, jnp.float32)
    u = jax.random.uniform(key, (3,))
    delay = p.delay_lo + jnp.floor(u[0] * (p.delay_hi - p.delay_lo + 1)).astype(jnp.int32)
    delay = jnp.minimum(delay, p.delay_hi)
    lead = (p.lead_lo + u[1] * (p.lead_hi - p.lead_lo)).astype(jnp.float32)
    left_first = u[2] < p.p_left_first
    return _PersonState(buf=jnp.zeros((_BUF, 2), jnp.float32), t=jnp.zeros((), jnp.int32),
                        delay=delay.astype(jnp.int32), lead=lead,
                        intent=jnp.where(left_first, -1.0, 1.0).astype(jnp.float32),
                        override=jnp.zeros((), jnp.float32), count=jnp.zeros((), jnp.int32),
                        p_hesitate=f(p.p_hesitate), hesitate_max=f(p.hesitate_max),
                        p_wrong=f(p.p_wrong), wrong_max=f(p.wrong_max),
                        p_coast=f(p.p_coast), coast_max=f(p.coast_max))


def _person_act(key, obs, ps: _PersonState):
    """One keyboard decision: obs float32 (2,) -> (action float32 (1,) in {-1,0,1}, state)."""
    obs = jnp.asarray(obs, jnp.float32)
    shifted = jnp.concatenate([obs[None], ps.buf[:-1]], axis=0)
    buf = jnp.where(ps.t == 0, jnp.broadcast_to(obs, ps.buf.shape), shifted)
    seen, before = buf[ps.delay], buf[ps.delay + 1]
    # Anticipated velocity: extrapolate the (delayed) velocity ``lead`` steps ahead.
    v_pred = seen[1] + ps.lead * (seen[1] - before[1])
    eps = 1e-4
    want = jnp.where(v_pred > eps, 1.0, jnp.where(v_pred < -eps, -1.0, ps.intent))
    want = jnp.where(ps.t <= ps.delay, ps.intent, want)  # nothing seen yet: the first key
    changed = want != ps.intent
    u = jax.random.uniform(key, (5,))  # one draw per step (cheap to compile)
    hes = changed & (u[0] < ps.p_hesitate)
    wrong = changed & (u[0] >= ps.p_hesitate) & (u[0] < ps.p_hesitate + ps.p_wrong)
    idle = ps.count <= 0
    coast = idle & jnp.logical_not(changed) & (u[1] < ps.p_coast)
    n_hes = 1 + jnp.floor(u[2] * ps.hesitate_max).astype(jnp.int32)
    n_wrong = 1 + jnp.floor(u[3] * ps.wrong_max).astype(jnp.int32)
    n_coast = 1 + jnp.floor(u[4] * ps.coast_max).astype(jnp.int32)
    count = jnp.where(hes, n_hes, jnp.where(wrong, n_wrong, jnp.where(coast, n_coast, ps.count)))
    override = jnp.where(hes | coast, 0.0, jnp.where(wrong, -want, ps.override))
    action = jnp.where(count > 0, override, want)
    new = ps._replace(buf=buf, t=ps.t + 1, intent=want.astype(jnp.float32),
                      override=override.astype(jnp.float32),
                      count=jnp.maximum(count - 1, 0).astype(jnp.int32))
    return jnp.reshape(action, (1,)).astype(jnp.float32), new


@functools.lru_cache(maxsize=None)
def simulated_person_policy(person: int) -> Policy:
    """The jittable policy of simulated person ``person`` in {0, 1, 2} (see :data:`PERSONS`).

    Observations are mountain-car obs float32 (2,) = [x, v]; actions float32 (1,) in
    {-1, 0, +1}. Deterministic given the keys. All persons share one ``act`` function (their
    habits travel in the policy state), so recording them compiles once."""
    if not 0 <= int(person) < len(PERSONS):
        raise ValueError(f"person must be in 0..{len(PERSONS) - 1}, got {person}")
    return Policy(init=functools.partial(_person_init, PERSONS[int(person)]), act=_person_act)


def person_of_run(n_runs: int) -> np.ndarray:
    """Which person drives run i: ``i % 3`` (11 runs -> 4, 4, 3 runs). int (n_runs,)."""
    return np.arange(n_runs) % len(PERSONS)


def simulated_person_demonstrations(seed: int = 0, n_runs: int = 11, max_steps: int = 1000,
                                    continuous: bool = False) -> Demonstrations:
    """``n_runs`` runs of the simulated people, all from the bottom of the hill (x=-0.5, v=0).

    Run ``i`` is driven by person ``i % 3`` (11 runs: 4, 4 and 3 runs) with key
    ``fold_in(PRNGKey(seed), i)``. Not capped at 200 steps (``max_steps`` is the recorder's
    limit; a run still going then is marked truncated). Deterministic in ``seed``. The actions
    are the discrete keys {-1, 0, +1}; ``continuous=True`` only labels the result for the
    continuous env (whose dynamics agree at those values).

    Returns Demonstrations (E = n_runs, env_id "mountain_car_discrete" or
    "mountain_car_continuous", source "simulated_person(seed=...)").
    """
    from envs.mountain_car import MountainCar, bottom_start

    n_runs = int(n_runs)
    if n_runs < 1:
        raise ValueError("n_runs must be >= 1")
    env = MountainCar(continuous=continuous)
    params = env.default_params()
    base = jax.random.PRNGKey(seed)
    ep_keys = jax.vmap(lambda i: jax.random.fold_in(base, i))(jnp.arange(n_runs))
    reset_keys, init_keys, run_keys = _episode_keys(ep_keys)
    inits = [_person_init(PERSONS[int(p)], init_keys[i])
             for i, p in enumerate(person_of_run(n_runs))]
    pstate0 = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *inits)
    return _run_recorder(env, params, _person_act, pstate0, reset_keys, run_keys, max_steps,
                         bottom_start(), f"simulated_person(seed={seed})")
