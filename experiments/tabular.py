"""Reference lines for mountain car: tabular Q-learning, the grid-DP optimum, the random policy.

The paper (Smart & Kaelbling 2000, section 3.1) compares HEDGER with "standard tabular
Q-learning on a finely discretised version of the problem, run until it converged" (56 steps);
The references add the optimal policy (~50 steps, grid dynamic programming) and the random policy
(~163 steps). This module measures all three on *exactly* the evaluation protocol of
``hedger_jax.agent.evaluate``: greedy policy, learning off, ``n_episodes`` (2500) starts from
``env.evaluation_starts`` (uniform x in [-1.2, 0.5), v in [-0.07, 0.07]), cap 200 steps, metric
= mean steps to the goal with a failure counted as 200. The dynamics are always the env's own
``MountainCar.step`` (discrete variant).

Everything is pure JAX with explicit PRNG keys; ``run_tabular`` is jittable and vmappable over
keys (seeds).

Tabular Q-learning (``TabularConfig``, defaults chosen by measurement, see ``reference_lines``):
  * grid: ``n_x x n_v`` = 100 x 100 uniform cells over [-1.2, 0.5] x [-0.07, 0.07]; a state maps
    to ``floor((s - low) / (high - low) * n)`` clipped into [0, n - 1] (the upper edges, x = 0.5
    and v = 0.07, fall into the last cell; anything outside is clipped to the border cells).
  * actions {-1, 0, +1} (indices 0, 1, 2).
  * reward ``"time"``: -1 on every step, gamma = 1 (undiscounted episodic, i.e. the return is
    minus the number of steps, so the greedy policy of the converged table is a minimum-time
    policy -- exactly the evaluation metric). Q starts at 0, which is optimistic and drives
    systematic exploration. The paper's own reward (``"paper"``: 0 except 1 - |v|/0.07 at the
    goal) with its gamma = 0.8 is available too; see ``reference_lines.json`` for how it fares.
    A time-limit truncation is not a terminal: the update bootstraps through it.
  * epsilon-greedy (ties among maximal actions broken at random), epsilon and alpha annealed
    linearly over the run from (``epsilon``, ``alpha``) to (``epsilon_final``, ``alpha_final``);
    training episodes start uniformly at random (``env.reset``) and last at most 200 steps.

Measured (``python -m experiments.tabular`` -> ``reference_lines.json``; evaluation key
PRNGKey(0), 2500 starts): tabular Q (reward "time", gamma 1, 100 x 100, 200,000 episodes,
seeds 0-2) 50.76 steps (per seed 50.78 / 50.69 / 50.82, each +-1.1 95% CI over starts);
with the paper's reward and gamma = 0.8 (seed 0, same budget) 55.36 -- it learns more slowly
(60.5 after 100,000 episodes vs 53.1) and its optimum trades time for a slow arrival, which is
why the minimum-time formulation is the default. Grid DP (301 x 301) 49.69 (101: 49.95,
601: 49.65); random policy 162.56 +- 2.9.

Grid DP (``solve_dp``): minimum time to goal ``T`` on an ``n x n`` lattice of nodes, value
iteration ``T(s) = min_a [1 + (1 - goal(s, a)) T(f(s, a))]`` with ``T(f(s, a))`` bilinearly
interpolated, ``f`` the env's step. The greedy policy evaluates the same one-step look-ahead at
the continuous state.
"""
from __future__ import annotations

import functools
import json
import os
import time
from typing import Any, Callable, Dict, NamedTuple, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from envs.mountain_car import MountainCar, MountainCarParams

__all__ = ["TabularConfig", "PolicyEvaluation", "ENV", "ACTIONS", "discretise",
           "run_tabular", "train_tabular", "tabular_greedy_action", "evaluate_tabular",
           "evaluate_policy", "random_policy_steps", "solve_dp", "dp_greedy_action",
           "optimal_policy_steps", "reference_lines", "REFERENCE_JSON", "REFERENCE_KEYS"]

#: The discrete mountain car with the paper's 200-step cap.
ENV = MountainCar(continuous=False, max_steps=200)
#: Action values, index i -> ACTIONS[i].
ACTIONS = jnp.array([-1.0, 0.0, 1.0], jnp.float32)
N_ACTIONS = 3

REFERENCE_JSON = os.path.join(os.path.dirname(os.path.abspath(__file__)), "reference_lines.json")
REFERENCE_KEYS = ("tabular_q", "optimal_dp", "random")


def _params(params: Optional[MountainCarParams]) -> MountainCarParams:
    return ENV.default_params() if params is None else params


def _bounds(params: MountainCarParams) -> Tuple[jax.Array, jax.Array]:
    """(low, high), float32 (2,) each: the state box [min_x, -vmax] x [max_x, vmax]."""
    return ENV.obs_bounds(params)


# --------------------------------------------------------------------------------------------
# Evaluation protocol (identical to hedger_jax.agent.evaluate)
# --------------------------------------------------------------------------------------------
class PolicyEvaluation(NamedTuple):
    """mean_steps float32 (); success_rate float32 (); steps float32 (n_episodes,) -- the steps
    of each episode, a failure counted as ``max_steps``."""
    mean_steps: jax.Array
    success_rate: jax.Array
    steps: jax.Array


def evaluate_policy(policy: Callable[[jax.Array, jax.Array], jax.Array], key: jax.Array,
                    n_episodes: int = 2500, params: Optional[MountainCarParams] = None,
                    max_steps: int = 200) -> PolicyEvaluation:
    """The paper's evaluation: ``n_episodes`` starts from ``ENV.evaluation_starts``, each run
    with ``policy(obs float32 (2,), key) -> action value float32 ()`` (vmapped) until it reaches
    the goal or ``max_steps``: ``hedger_jax.agent.evaluate_policy``, the loop HEDGER's own
    evaluation uses.
    """
    from hedger_jax.agent import evaluate_policy as run_policy

    steps, success = run_policy(ENV, _params(params), policy, key, n_episodes, max_steps)
    return PolicyEvaluation(jnp.mean(steps), jnp.mean(success.astype(jnp.float32)), steps)


def summarise(ev: PolicyEvaluation) -> Dict[str, float]:
    """Host-side: mean steps, standard error, 95% CI half-width (normal), success rate."""
    steps = np.asarray(ev.steps, np.float64)
    se = float(steps.std(ddof=1) / np.sqrt(steps.size)) if steps.size > 1 else 0.0
    return {"mean_steps": float(steps.mean()), "se": se, "ci95": 1.96 * se,
            "success_rate": float(np.asarray(ev.success_rate)), "n_episodes": int(steps.size)}


# --------------------------------------------------------------------------------------------
# Random policy
# --------------------------------------------------------------------------------------------
def _random_policy(obs: jax.Array, key: jax.Array) -> jax.Array:
    del obs
    return ACTIONS[jax.random.randint(key, (), 0, N_ACTIONS)]


@functools.partial(jax.jit, static_argnames=("n_episodes",))
def random_policy_steps(key: jax.Array, n_episodes: int = 2500) -> PolicyEvaluation:
    """The uniformly random policy over {-1, 0, +1} under the evaluation protocol."""
    return evaluate_policy(_random_policy, key, n_episodes)


# --------------------------------------------------------------------------------------------
# Tabular Q-learning
# --------------------------------------------------------------------------------------------
class TabularConfig(NamedTuple):
    """Static settings of tabular Q-learning (hashable: a jit static argument).

    n_x, n_v: grid cells per dimension. alpha -> alpha_final, epsilon -> epsilon_final: linear
    annealing over the run's episodes. gamma: discount. reward: "time" (-1 per step) or "paper"
    (the env's reward: 0, and 1 - |v|/0.07 on reaching the goal). q_init: initial Q value.
    max_steps: training episode cap.
    """
    n_x: int = 100
    n_v: int = 100
    alpha: float = 0.5
    alpha_final: float = 0.05
    gamma: float = 1.0
    epsilon: float = 0.1
    epsilon_final: float = 0.0
    reward: str = "time"
    q_init: float = 0.0
    max_steps: int = 200


def discretise(obs: jax.Array, n_x: int, n_v: int,
               params: Optional[MountainCarParams] = None) -> Tuple[jax.Array, jax.Array]:
    """Cell of a state: obs float32 (..., 2) = [x, v] -> (ix int32 (...), iv int32 (...)).

    ``i = floor((s - low) / (high - low) * n)`` clipped into [0, n - 1]: cells are half-open
    [low + i w, low + (i + 1) w) except the last, which also holds the upper edge; states outside
    the box are clipped to the border cells."""
    low, high = _bounds(_params(params))
    u = (jnp.asarray(obs, jnp.float32) - low) / (high - low)
    ix = jnp.clip(jnp.floor(u[..., 0] * n_x), 0, n_x - 1).astype(jnp.int32)
    iv = jnp.clip(jnp.floor(u[..., 1] * n_v), 0, n_v - 1).astype(jnp.int32)
    return ix, iv


def _argmax_random_ties(q: jax.Array, key: jax.Array) -> jax.Array:
    """q (3,) -> int32 (): an index of a maximum, uniformly among ties."""
    best = q >= jnp.max(q)
    noise = jax.random.uniform(key, q.shape)
    return jnp.argmax(jnp.where(best, noise, -1.0)).astype(jnp.int32)


def _schedule(start: float, end: float, frac: jax.Array) -> jax.Array:
    return jnp.float32(start) + (jnp.float32(end) - jnp.float32(start)) * frac


def train_tabular(q: jax.Array, key: jax.Array, n_episodes: int, config: TabularConfig,
                  episode_offset: int = 0, total_episodes: Optional[int] = None,
                  params: Optional[MountainCarParams] = None) -> Tuple[jax.Array, jax.Array]:
    """Continue Q-learning for ``n_episodes`` episodes (``lax.scan``; one ``while_loop`` per
    episode). Jittable (``n_episodes``, ``config``, ``total_episodes`` static) and vmappable over
    ``q``/``key``.

    Args:
      q: float32 (n_x, n_v, 3), the table.
      key: PRNG key.
      episode_offset: index of the first episode in the whole run (for the annealing).
      total_episodes: length of the whole run (annealing horizon); default ``n_episodes``.
    Returns:
      (q float32 (n_x, n_v, 3), lengths int32 (n_episodes,) -- training episode lengths).
    """
    params = _params(params)
    total = n_episodes if total_episodes is None else total_episodes
    cfg = config

    def episode(q, xs):
        ep, k = xs
        frac = jnp.clip(ep.astype(jnp.float32) / max(total - 1, 1), 0.0, 1.0)
        alpha = _schedule(cfg.alpha, cfg.alpha_final, frac)
        eps = _schedule(cfg.epsilon, cfg.epsilon_final, frac)
        k_reset, k_loop = jax.random.split(k)
        obs, state = ENV.reset(k_reset, params)

        def cond(c):
            return ~c[3]

        def body(c):
            q, obs, state, done, key = c
            key, k_eps, k_rand, k_tie, k_step = jax.random.split(key, 5)
            ix, iv = discretise(obs, cfg.n_x, cfg.n_v, params)
            greedy = _argmax_random_ties(q[ix, iv], k_tie)
            explore = jax.random.uniform(k_eps) < eps
            a = jnp.where(explore, jax.random.randint(k_rand, (), 0, N_ACTIONS), greedy)
            nobs, nstate, r, term, trunc, _ = ENV.step(k_step, state, ACTIONS[a], params)
            if cfg.reward == "time":
                r = jnp.float32(-1.0)
            jx, jv = discretise(nobs, cfg.n_x, cfg.n_v, params)
            boot = jnp.where(term, 0.0, jnp.max(q[jx, jv]))
            target = r + jnp.float32(cfg.gamma) * boot
            q = q.at[ix, iv, a].add(alpha * (target - q[ix, iv, a]))
            done = term | trunc | (nstate.time >= cfg.max_steps)
            return q, nobs, nstate, done, key

        q, _, state, _, _ = jax.lax.while_loop(
            cond, body, (q, obs, state, jnp.zeros((), bool), k_loop))
        return q, state.time

    eps_idx = jnp.arange(n_episodes, dtype=jnp.int32) + episode_offset
    keys = jax.random.split(key, n_episodes)
    return jax.lax.scan(episode, q, (eps_idx, keys))


def init_table(config: TabularConfig) -> jax.Array:
    """float32 (n_x, n_v, 3) filled with ``config.q_init``."""
    return jnp.full((config.n_x, config.n_v, N_ACTIONS), config.q_init, jnp.float32)


@functools.partial(jax.jit, static_argnames=("n_episodes", "config"))
def run_tabular(key: jax.Array, n_episodes: int,
                config: TabularConfig = TabularConfig()) -> Tuple[jax.Array, jax.Array]:
    """A whole tabular Q-learning run from a fresh table.

    Returns (q_table float32 (n_x, n_v, 3), curve int32 (n_episodes,) = training episode
    lengths). Vmappable over ``key``: ``jax.vmap(run_tabular, (0, None, None))`` needs the
    statics bound, e.g. ``jax.vmap(lambda k: run_tabular(k, n, cfg))(keys)``."""
    return train_tabular(init_table(config), key, n_episodes, config)


def tabular_greedy_action(q_table: jax.Array, obs: jax.Array,
                          params: Optional[MountainCarParams] = None) -> jax.Array:
    """Greedy action value: q_table (n_x, n_v, 3), obs (2,) -> float32 () in {-1, 0, 1}
    (ties -> the lowest index)."""
    n_x, n_v = q_table.shape[0], q_table.shape[1]
    ix, iv = discretise(obs, n_x, n_v, params)
    return ACTIONS[jnp.argmax(q_table[ix, iv])]


@functools.partial(jax.jit, static_argnames=("n_episodes",))
def evaluate_tabular(q_table: jax.Array, key: jax.Array,
                     n_episodes: int = 2500) -> PolicyEvaluation:
    """Greedy policy of ``q_table`` (n_x, n_v, 3) under the evaluation protocol."""
    return evaluate_policy(lambda obs, k: tabular_greedy_action(q_table, obs), key, n_episodes)


# --------------------------------------------------------------------------------------------
# Grid dynamic programming (minimum time to goal)
# --------------------------------------------------------------------------------------------
def _grid_axes(n_x: int, n_v: int, params: MountainCarParams) -> Tuple[jax.Array, jax.Array]:
    low, high = _bounds(params)
    return (jnp.linspace(low[0], high[0], n_x, dtype=jnp.float32),
            jnp.linspace(low[1], high[1], n_v, dtype=jnp.float32))


def _interp_weights(obs: jax.Array, n_x: int, n_v: int, params: MountainCarParams):
    """Bilinear interpolation on the node lattice: obs (..., 2) -> (i0, j0 int32 (...),
    wx, wv float32 (...)), value = sum of the 4 corners (i0 + di, j0 + dj) weighted."""
    low, high = _bounds(params)
    u = jnp.clip((obs - low) / (high - low), 0.0, 1.0)
    gx, gv = u[..., 0] * (n_x - 1), u[..., 1] * (n_v - 1)
    i0 = jnp.clip(jnp.floor(gx), 0, n_x - 2).astype(jnp.int32)
    j0 = jnp.clip(jnp.floor(gv), 0, n_v - 2).astype(jnp.int32)
    return i0, j0, gx - i0, gv - j0


def _interp(T: jax.Array, i0, j0, wx, wv) -> jax.Array:
    return ((1 - wx) * (1 - wv) * T[i0, j0] + wx * (1 - wv) * T[i0 + 1, j0]
            + (1 - wx) * wv * T[i0, j0 + 1] + wx * wv * T[i0 + 1, j0 + 1])


def _successors(obs: jax.Array, params: MountainCarParams):
    """obs (..., 2) -> (next obs (..., 3, 2), terminated bool (..., 3)) for each action."""
    def one(o, a):
        _, st = ENV.reset_to(None, params, o)
        nobs, _, _, term, _, _ = ENV.step(None, st, a, params)
        return nobs, term
    flat = obs.reshape(-1, 2)
    nobs, term = jax.vmap(lambda o: jax.vmap(lambda a: one(o, a))(ACTIONS))(flat)
    return nobs.reshape(obs.shape[:-1] + (N_ACTIONS, 2)), term.reshape(obs.shape[:-1] + (N_ACTIONS,))


@functools.partial(jax.jit, static_argnames=("n_x", "n_v", "max_iters"))
def solve_dp(n_x: int = 301, n_v: int = 301, max_iters: int = 1000, tol: float = 1e-4,
             params: Optional[MountainCarParams] = None) -> Tuple[jax.Array, jax.Array]:
    """Minimum time to goal on an ``n_x x n_v`` node lattice (value iteration from T = 0).

    Returns (T float32 (n_x, n_v), n_iters int32 ()): T(s) = expected steps to the goal from
    node s under the greedy policy of the interpolated model; iteration stops when the largest
    change is below ``tol`` or after ``max_iters`` sweeps."""
    params = _params(params)
    xs, vs = _grid_axes(n_x, n_v, params)
    nodes = jnp.stack(jnp.meshgrid(xs, vs, indexing="ij"), -1)          # (n_x, n_v, 2)
    nobs, term = _successors(nodes, params)                            # (n_x, n_v, 3, ...)
    w = _interp_weights(nobs, n_x, n_v, params)

    def backup(T):
        return jnp.min(1.0 + jnp.where(term, 0.0, _interp(T, *w)), axis=-1)

    def cond(c):
        return (c[2] < max_iters) & (c[1] > tol)

    def body(c):
        T, _, it = c
        Tn = backup(T)
        return Tn, jnp.max(jnp.abs(Tn - T)), it + 1

    T, _, it = jax.lax.while_loop(
        cond, body, (jnp.zeros((n_x, n_v), jnp.float32), jnp.float32(jnp.inf), jnp.int32(0)))
    return T, it


def dp_greedy_action(T: jax.Array, obs: jax.Array,
                     params: Optional[MountainCarParams] = None) -> jax.Array:
    """One-step look-ahead on the interpolated time-to-goal ``T`` (n_x, n_v): obs (2,) ->
    action value float32 () minimising 1 + (not goal) T(f(obs, a))."""
    params = _params(params)
    n_x, n_v = T.shape
    nobs, term = _successors(obs, params)                              # (3, 2), (3,)
    cost = 1.0 + jnp.where(term, 0.0, _interp(T, *_interp_weights(nobs, n_x, n_v, params)))
    return ACTIONS[jnp.argmin(cost)]


@functools.partial(jax.jit, static_argnames=("n_episodes",))
def evaluate_dp(T: jax.Array, key: jax.Array, n_episodes: int = 2500) -> PolicyEvaluation:
    """The DP greedy policy of ``T`` (n_x, n_v) under the evaluation protocol."""
    return evaluate_policy(lambda obs, k: dp_greedy_action(T, obs), key, n_episodes)


def optimal_policy_steps(key: jax.Array, n_episodes: int = 2500, n_grid: int = 301,
                         ) -> Tuple[PolicyEvaluation, jax.Array]:
    """Solve the DP on an ``n_grid x n_grid`` lattice and evaluate its greedy policy.

    Returns (PolicyEvaluation, T float32 (n_grid, n_grid))."""
    T, _ = solve_dp(n_grid, n_grid)
    return evaluate_dp(T, key, n_episodes), T


# --------------------------------------------------------------------------------------------
# Reference lines (computed on demand, cached as JSON)
# --------------------------------------------------------------------------------------------
#: Settings of the committed measurement (``python -m experiments.tabular``).
REFERENCE_SETTINGS = dict(
    eval_seed=0, n_eval_episodes=2500,
    tabular_seeds=(0, 1, 2), tabular_episodes=200_000, tabular_config=TabularConfig()._asdict(),
    dp_grid=301, dp_grid_check=(101, 601), random_seed=0,
    # The paper's own reward (0, and 1 - |v|/0.07 at the goal) with its gamma = 0.8, same grid
    # and schedules: measured for comparison only (it learns more slowly; see the JSON).
    paper_reward_seeds=(0,), paper_reward_config=TabularConfig(reward="paper", gamma=0.8)._asdict(),
)


def compute_reference_lines(settings: Optional[Dict[str, Any]] = None,
                            verbose: bool = False) -> Dict[str, Any]:
    """Measure the three reference lines (minutes for the committed settings).

    Returns {"tabular_q": {...}, "optimal_dp": {...}, "random": {...}, "settings": {...}}; each
    line has mean_steps (for tabular Q the mean over seeds of each seed's evaluation), se, ci95,
    success_rate and its own settings."""
    s = dict(REFERENCE_SETTINGS, **(settings or {}))
    eval_key = jax.random.PRNGKey(s["eval_seed"])
    n_eval = int(s["n_eval_episodes"])
    out: Dict[str, Any] = {}

    t0 = time.time()
    rnd = summarise(random_policy_steps(jax.random.PRNGKey(s["random_seed"]), n_eval))
    rnd["seed"] = s["random_seed"]
    out["random"] = rnd
    if verbose:
        print(f"random: {rnd} ({time.time() - t0:.0f}s)", flush=True)

    t0 = time.time()
    T, iters = solve_dp(s["dp_grid"], s["dp_grid"])
    dp = summarise(evaluate_dp(T, eval_key, n_eval))
    dp.update(grid=int(s["dp_grid"]), value_iterations=int(iters),
              T_bottom=float(dp_greedy_steps_from_bottom(T)))
    dp["grid_check"] = {}
    for n in s.get("dp_grid_check", ()):
        Tn, _ = solve_dp(int(n), int(n))
        dp["grid_check"][str(n)] = summarise(evaluate_dp(Tn, eval_key, n_eval))["mean_steps"]
    out["optimal_dp"] = dp
    if verbose:
        print(f"optimal_dp: {dp} ({time.time() - t0:.0f}s)", flush=True)

    for name, cfg_key, seeds_key in (("tabular_q", "tabular_config", "tabular_seeds"),
                                     ("tabular_q_paper_reward", "paper_reward_config",
                                      "paper_reward_seeds")):
        if not s.get(seeds_key):
            continue
        t0 = time.time()
        tab = _measure_tabular(TabularConfig(**s[cfg_key]), s[seeds_key],
                               int(s["tabular_episodes"]), eval_key, n_eval, verbose)
        tab["seconds"] = round(time.time() - t0, 1)
        out[name] = tab
        if verbose:
            print(f"{name}: {tab}", flush=True)
    out["settings"] = {k: (list(v) if isinstance(v, tuple) else v) for k, v in s.items()}
    return out


def _measure_tabular(cfg: TabularConfig, seeds, n_train: int, eval_key: jax.Array,
                     n_eval: int, verbose: bool = False) -> Dict[str, Any]:
    """Train one table per seed (vmapped), evaluate each greedily; mean and between-seed SE."""
    per_seed, finals = [], []
    for k in seeds:   # one seed at a time (a vmapped run waits for the longest episode)
        q, curve = run_tabular(jax.random.PRNGKey(int(k)), n_train, cfg)
        per_seed.append(summarise(evaluate_tabular(q, eval_key, n_eval)))
        if verbose:
            print(f"  seed {k}: {per_seed[-1]}", flush=True)
        finals.append(float(np.asarray(curve[-1000:]).mean()))
    means = np.array([p["mean_steps"] for p in per_seed])
    se_between = float(means.std(ddof=1) / np.sqrt(means.size)) if means.size > 1 else 0.0
    return {"mean_steps": float(means.mean()), "se": se_between, "ci95": 1.96 * se_between,
            "per_seed_mean_steps": means.tolist(),
            "per_seed_se": [p["se"] for p in per_seed],
            "success_rate": float(np.mean([p["success_rate"] for p in per_seed])),
            "n_episodes": n_eval, "seeds": [int(k) for k in seeds], "train_episodes": n_train,
            "config": cfg._asdict(),
            "final_train_length_mean": float(np.mean(finals))}


def dp_greedy_steps_from_bottom(T: jax.Array) -> jax.Array:
    """Interpolated time-to-goal at the bottom of the hill (x = -0.5, v = 0): float32 ()."""
    params = _params(None)
    n_x, n_v = T.shape
    return _interp(T, *_interp_weights(jnp.array([-0.5, 0.0], jnp.float32), n_x, n_v, params))


def reference_lines(cache_path: Optional[str] = None, recompute: bool = False,
                    full: bool = False) -> Dict[str, Any]:
    """The reference lines for the figures: {"tabular_q": float, "optimal_dp": float,
    "random": float} (mean steps), read from ``cache_path`` (default ``REFERENCE_JSON``) or,
    if missing/invalid or ``recompute``, measured with ``REFERENCE_SETTINGS`` and written there.
    ``full=True`` returns the whole record (standard errors, settings, seeds)."""
    path = REFERENCE_JSON if cache_path is None else cache_path
    data = None
    if not recompute:
        try:
            with open(path) as f:
                data = json.load(f)
            if not all(isinstance(data.get(k), dict) and "mean_steps" in data[k]
                       for k in REFERENCE_KEYS):
                data = None
        except (OSError, ValueError):
            data = None
    if data is None:
        data = compute_reference_lines()
        tmp = path + ".tmp"
        with open(tmp, "w") as f:
            json.dump(data, f, indent=2, sort_keys=True)
            f.write("\n")
        os.replace(tmp, path)
    if full:
        return data
    return {k: float(data[k]["mean_steps"]) for k in REFERENCE_KEYS}


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=REFERENCE_JSON)
    args = parser.parse_args()
    data = compute_reference_lines(verbose=True)
    with open(args.out, "w") as f:
        json.dump(data, f, indent=2, sort_keys=True)
        f.write("\n")
    print({k: data[k]["mean_steps"] for k in REFERENCE_KEYS})
