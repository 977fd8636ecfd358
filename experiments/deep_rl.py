"""HEDGER against deep RL (SB3 DQN, PPO, SAC with the RL Baselines3 Zoo's tuned settings).

``python -m experiments.deep_rl [--methods hedger hedger-demos dqn sac ppo]
[--protocols gymnasium random] [--seeds 5] [--out results/deep_rl] [--steps dqn=120000 ...]
[--docs DIR] [--summary-only]``

Mountain car, two start protocols, used for training *and* evaluation:

* ``gymnasium``: Gymnasium's own reset, x ~ U[-0.6, -0.4], v = 0;
* ``random``: the paper's starts, x ~ U[-1.2, 0.5), v ~ U[-0.07, 0.07) (``StartWrapper``
  sets ``env.unwrapped.state`` after Gymnasium's reset, drawing from the env's own seeded
  generator).

Methods (``METHODS``): ``hedger`` (discrete actions, no demonstrations), ``hedger-demos``
(the 11 simulated-person demonstrations first, then phase two), ``hedger-continuous``
(continuous actions with the demonstrations; optional), and SB3's ``dqn``, ``ppo`` (both on
MountainCar-v0 and its reward, -1 per step, 200-step cap) and ``sac`` (on
MountainCarContinuous-v0, its reward and its 999-step limit, as the Zoo tunes it; it is a
different car: power 0.0015 instead of force 0.001, goal at x >= 0.45 instead of 0.5).
HEDGER runs on ``envs.mountain_car.MountainCar`` (Gymnasium's MountainCar-v0 dynamics; the
paper's reward, 0 except at the goal) with Figure 2's settings.

Evaluation: the greedy / deterministic policy, learning off, on ``EVAL_EPISODES`` episodes
every ``eval_every`` env steps (SB3: Gymnasium envs reset with seeds ``EVAL_SEED + i``, the
same starts for every method, seed and evaluation; HEDGER: the library's in-program
evaluation, same start distribution, starts drawn from the run's key), steps to the goal
with failures counted as ``CAP`` = 200; then a final evaluation on ``FINAL_EPISODES``
episodes, which is the curve's last point. SAC's policy is evaluated on
MountainCarContinuous-v0 (the car it learned), capped at 200 steps. HEDGER's env steps
count its demonstrations' steps.

Reported per method and protocol (``summarize``): env steps at the first evaluation whose
mean is <= ``TARGET`` = 110 (mean and 95 % t-interval over the seeds that reached it, and
how many did), the final steps to the goal, and wall-clock seconds per run.

One JSON per (method, protocol, seed) in ``--out``, written atomically when the run ends;
a rerun skips those that exist, so a killed sweep resumes (the run in progress restarts).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from typing import Any, Callable, Dict, List, Optional, Sequence

import numpy as np

from experiments.stats import mean_ci

METHODS = ("hedger", "hedger-demos", "hedger-continuous", "dqn", "ppo", "sac")
DEFAULT_METHODS = ("hedger", "hedger-demos", "dqn", "sac", "ppo")
PROTOCOLS = ("gymnasium", "random")
SB3_METHODS = ("dqn", "ppo", "sac")
#: Names in the plot's legends.
LABELS = {"hedger": "HEDGER", "hedger-demos": "HEDGER + 11 demonstrations",
          "hedger-continuous": "HEDGER continuous + 11 demonstrations",
          "dqn": "SB3 DQN (Zoo)", "ppo": "SB3 PPO (Zoo)",
          "sac": "SB3 SAC (Zoo; MountainCarContinuous-v0)"}

#: Start ranges: (x_low, x_high, v_low, v_high); x_high (and v_high) exclusive.
STARTS = {"gymnasium": (-0.6, -0.4, 0.0, 0.0), "random": (-1.2, 0.5, -0.07, 0.07)}
CAP = 200                   # evaluation cap; a failure counts as CAP steps
TARGET = 110.0              # "steps to first reach <= TARGET steps-to-goal"
EVAL_EPISODES = 20          # episodes per evaluation on the curve
FINAL_EPISODES = 100        # episodes of the final evaluation
EVAL_SEED = 10_000          # evaluation episode i resets with seed EVAL_SEED + i

#: RL Baselines3 Zoo, hyperparams/dqn.yml, ppo.yml and sac.yml (checked against the Zoo's
#: repository at commit 22e3ff2, April 2026). ``n_timesteps`` is the Zoo's budget; the budget
#: run here is ``BUDGET`` (see docs/deep_rl.md for why some are shorter).
ZOO: Dict[str, Dict[str, Any]] = {
    "dqn": dict(env="MountainCar-v0", n_timesteps=120_000, policy="MlpPolicy",
                learning_rate=4e-3, batch_size=128, buffer_size=10_000, learning_starts=1000,
                gamma=0.98, target_update_interval=600, train_freq=16, gradient_steps=8,
                exploration_fraction=0.2, exploration_final_eps=0.07,
                policy_kwargs=dict(net_arch=[256, 256])),
    "ppo": dict(env="MountainCar-v0", n_timesteps=1_000_000, policy="MlpPolicy",
                normalize=True, n_envs=16, n_steps=16, gae_lambda=0.98, gamma=0.99,
                n_epochs=4, ent_coef=0.0),
    "sac": dict(env="MountainCarContinuous-v0", n_timesteps=50_000, policy="MlpPolicy",
                learning_rate=3e-4, buffer_size=50_000, batch_size=512, ent_coef=0.1,
                train_freq=32, gradient_steps=32, gamma=0.9999, tau=0.01, learning_starts=0,
                use_sde=True, policy_kwargs=dict(log_std_init=-3.67, net_arch=[64, 64])),
}

#: Env steps per run (defaults; ``--steps method=N`` overrides). DQN runs the Zoo's budget;
#: PPO and SAC are capped to fit 2 shared cores (docs/deep_rl.md).
BUDGET = {"dqn": 120_000, "ppo": 300_000, "sac": 20_000}
#: Env steps between evaluations on the curve.
EVAL_EVERY = {"dqn": 10_000, "ppo": 20_000, "sac": 2_500}

#: HEDGER: Figure 2's settings (experiments/figures.py MOUNTAIN_CAR / _CONTINUOUS), phase-two
#: episodes, and episodes per evaluation block.
HEDGER_EPISODES = 600
HEDGER_BLOCK = 20


# ------------------------------------------------------------------------------------------
# Environments and evaluation (Gymnasium)
# ------------------------------------------------------------------------------------------
def _start_wrapper_class():
    import gymnasium as gym

    class StartWrapper(gym.Wrapper):
        """Resets from a protocol's starts. ``gymnasium``: Gymnasium's own reset, unchanged;
        ``random``: after it, ``x ~ U[-1.2, 0.5)``, ``v ~ U[-0.07, 0.07)`` from the env's
        seeded generator, written into ``env.unwrapped.state``."""

        def __init__(self, env, protocol: str):
            if protocol not in PROTOCOLS:
                raise ValueError(f"protocol must be one of {PROTOCOLS}, got {protocol!r}")
            super().__init__(env)
            self.protocol = protocol

        def reset(self, *, seed=None, options=None):
            obs, info = self.env.reset(seed=seed, options=options)
            if self.protocol == "gymnasium":
                return obs, info
            base = self.env.unwrapped
            x_lo, x_hi, v_lo, v_hi = STARTS[self.protocol]
            x = base.np_random.uniform(x_lo, x_hi)
            v = base.np_random.uniform(v_lo, v_hi)
            base.state = np.array([x, v], dtype=np.asarray(base.state).dtype)
            return np.array(base.state, dtype=np.float32), info

    return StartWrapper


def make_env(protocol: str, continuous: bool = False):
    """Gymnasium's MountainCar-v0 (or MountainCarContinuous-v0, ``continuous``), with its own
    time limit, reset from ``protocol``'s starts."""
    import gymnasium as gym

    env = gym.make("MountainCarContinuous-v0" if continuous else "MountainCar-v0")
    return _start_wrapper_class()(env, protocol)


def evaluate_steps(act: Callable[[np.ndarray], np.ndarray], protocol: str, n_episodes: int,
                   continuous: bool = False, seed: int = EVAL_SEED,
                   cap: int = CAP) -> np.ndarray:
    """Steps to the goal of ``n_episodes`` episodes on Gymnasium's env (``make_env``), episode
    ``i`` reset with seed ``seed + i``, run side by side: ``act(obs float32 (n, 2)) ->
    actions (n,) or (n, 1)`` for the episodes still running. An episode counts the steps
    up to Gymnasium's ``terminated`` (the goal); one not there after ``cap`` steps (or
    truncated before) counts ``cap``. Returns float64 (n_episodes,)."""
    envs = [make_env(protocol, continuous) for _ in range(n_episodes)]
    obs = np.stack([e.reset(seed=seed + i)[0] for i, e in enumerate(envs)]).astype(np.float32)
    steps = np.full(n_episodes, float(cap))
    running = np.ones(n_episodes, bool)
    for t in range(1, cap + 1):
        idx = np.flatnonzero(running)
        if idx.size == 0:
            break
        actions = np.asarray(act(obs[idx]))
        for j, i in enumerate(idx):
            a = actions[j]
            a = np.asarray(a, np.float32).reshape(1) if continuous else int(np.asarray(a).item())
            o, _, terminated, truncated, _ = envs[i].step(a)
            obs[i] = o
            if terminated:
                steps[i], running[i] = t, False
            elif truncated:
                running[i] = False
    for e in envs:
        e.close()
    return steps


def first_reach(env_steps: Sequence[float], mean_steps: Sequence[float],
                target: float = TARGET) -> Optional[float]:
    """The env steps of the first evaluation whose mean steps-to-goal is <= ``target``;
    None when none is."""
    for x, y in zip(env_steps, mean_steps):
        if y <= target:
            return float(x)
    return None


# ------------------------------------------------------------------------------------------
# SB3 runs
# ------------------------------------------------------------------------------------------
def _sb3_model(method: str, protocol: str, seed: int):
    """The Zoo-configured SB3 model on the protocol's training env."""
    from stable_baselines3 import DQN, PPO, SAC
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    hp = {k: v for k, v in ZOO[method].items() if k not in ("env", "n_timesteps", "normalize",
                                                             "n_envs", "policy")}
    common = dict(seed=seed, device="cpu", verbose=0)
    if method == "dqn":
        return DQN(ZOO[method]["policy"], make_env(protocol), **hp, **common)
    if method == "sac":
        return SAC(ZOO[method]["policy"], make_env(protocol, continuous=True), **hp, **common)
    if method == "ppo":
        venv = make_vec_env(lambda: make_env(protocol), n_envs=ZOO["ppo"]["n_envs"], seed=seed)
        # The Zoo's ``normalize: true``: observations and rewards, with the algorithm's gamma.
        venv = VecNormalize(venv, gamma=ZOO["ppo"]["gamma"])
        return PPO(ZOO[method]["policy"], venv, **hp, **common)
    raise ValueError(f"not an SB3 method: {method!r}")


def _sb3_act(model) -> Callable[[np.ndarray], np.ndarray]:
    """The deterministic policy on raw observations (normalised as in training for PPO)."""
    vec_norm = model.get_vec_normalize_env()

    def act(obs):
        if vec_norm is not None:
            obs = vec_norm.normalize_obs(obs)
        return model.predict(obs, deterministic=True)[0]

    return act


def run_sb3(method: str, protocol: str, seed: int, steps: int, eval_every: int,
            eval_episodes: int = EVAL_EPISODES,
            final_episodes: int = FINAL_EPISODES) -> Dict[str, Any]:
    """Train an SB3 method for ``steps`` env steps, evaluating every ``eval_every``."""
    import torch
    from stable_baselines3.common.callbacks import BaseCallback

    torch.set_num_threads(1)
    continuous = method == "sac"
    curve_x: List[int] = []
    curve_y: List[float] = []
    curve_success: List[float] = []
    eval_s = [0.0]

    def record(model, n_episodes):
        t0 = time.perf_counter()
        s = evaluate_steps(_sb3_act(model), protocol, n_episodes, continuous)
        eval_s[0] += time.perf_counter() - t0
        curve_x.append(int(model.num_timesteps))
        curve_y.append(float(s.mean()))
        curve_success.append(float((s < CAP).mean()))
        return s

    class Evaluations(BaseCallback):
        def __init__(self):
            super().__init__()
            self.next = eval_every

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next and self.num_timesteps < steps:
                record(self.model, eval_episodes)
                while self.next <= self.num_timesteps:
                    self.next += eval_every
            return True

    t0 = time.perf_counter()
    model = _sb3_model(method, protocol, seed)
    model.learn(total_timesteps=steps, callback=Evaluations())
    final = record(model, final_episodes)
    wall = time.perf_counter() - t0
    return {"env_steps": curve_x, "mean_steps": curve_y, "success_rate": curve_success,
            "final_steps": float(final.mean()), "final_per_episode": final.tolist(),
            "wall_s": wall, "eval_s": eval_s[0], "train_s": wall - eval_s[0],
            "budget": steps, "eval_every": eval_every,
            "hyperparameters": {k: (str(v) if isinstance(v, dict) else v)
                                for k, v in ZOO[method].items()}}


# ------------------------------------------------------------------------------------------
# HEDGER runs
# ------------------------------------------------------------------------------------------
_HEDGER_CACHE: Dict[Any, Any] = {}


def hedger_env_params(env: Any, protocol: str) -> Any:
    """``env``'s (``envs.mountain_car.MountainCar``) default params with ``protocol``'s start
    ranges, for its training and evaluation resets."""
    x_lo, x_hi, v_lo, v_hi = STARTS[protocol]
    return dataclasses.replace(
        env.default_params(), start_position_low=np.float32(x_lo),
        start_position_high=np.float32(x_hi), start_velocity_low=np.float32(v_lo),
        start_velocity_high=np.float32(v_hi))


def _hedger_program(method: str, protocol: str, episodes: int, block: int,
                    eval_episodes: int, final_episodes: int):
    """(compiled train, compiled final evaluation, compile seconds, settings), built once per
    (method, protocol, lengths) in this process."""
    cache_key = (method, protocol, episodes, block, eval_episodes, final_episodes)
    if cache_key in _HEDGER_CACHE:
        return _HEDGER_CACHE[cache_key]
    import jax

    from envs.mountain_car import MountainCar
    from experiments.figures import MOUNTAIN_CAR, MOUNTAIN_CAR_CONTINUOUS
    from hedger_jax import HedgerConfig, RunConfig, cpu, make_train
    from hedger_jax.agent import evaluate, transitions_from_demonstrations

    continuous = method == "hedger-continuous"
    demos = method in ("hedger-demos", "hedger-continuous")
    env = MountainCar(continuous=continuous)
    env_params = hedger_env_params(env, protocol)
    settings = dict(MOUNTAIN_CAR_CONTINUOUS if continuous else MOUNTAIN_CAR)
    phase1 = None
    if demos:
        from envs.demonstrators import simulated_person_demonstrations

        phase1 = transitions_from_demonstrations(
            simulated_person_demonstrations(seed=0, continuous=continuous))
    n_blocks = max(1, episodes // block)
    capacity = n_blocks * block * env.max_steps + 5_000
    config = HedgerConfig.for_env(env, capacity=capacity, **settings)
    run_cfg = RunConfig(n_blocks=n_blocks, episodes_per_block=block,
                        eval_episodes=eval_episodes, eval_max_steps=CAP)
    train = make_train(env, config, run_cfg, env_params=env_params, phase1=phase1).train

    def final_eval(memory, key):
        return evaluate(env, env_params, config, memory, key, final_episodes, CAP)

    key0 = jax.random.PRNGKey(0)
    t0 = time.perf_counter()
    train_c = cpu.jit(train).lower(key0).compile()
    state_shape = jax.eval_shape(train, key0)[0]
    final_c = cpu.jit(final_eval).lower(state_shape.memory, key0).compile()
    compile_s = time.perf_counter() - t0
    info = dict(settings, capacity=capacity, phase2_episodes=n_blocks * block,
                episodes_per_block=block, epsilon=run_cfg.epsilon, demonstrations=demos,
                continuous=continuous)
    _HEDGER_CACHE[cache_key] = (train_c, final_c, compile_s, info)
    return _HEDGER_CACHE[cache_key]


def run_hedger(method: str, protocol: str, seed: int, episodes: int = HEDGER_EPISODES,
               block: int = HEDGER_BLOCK, eval_episodes: int = EVAL_EPISODES,
               final_episodes: int = FINAL_EPISODES) -> Dict[str, Any]:
    """One HEDGER run: phase 1 (demonstrations, for the ``-demos`` / ``-continuous``
    methods), then ``episodes`` phase-two episodes, evaluated after phase 1 and every
    ``block`` episodes; the final evaluation on ``final_episodes`` episodes."""
    import jax

    train_c, final_c, compile_s, info = _hedger_program(method, protocol, episodes, block,
                                                        eval_episodes, final_episodes)
    key = jax.random.fold_in(jax.random.PRNGKey(0), seed)
    t0 = time.perf_counter()
    state, res = jax.block_until_ready(train_c(key))
    final = jax.block_until_ready(final_c(state.memory, jax.random.fold_in(key, 99)))
    wall = time.perf_counter() - t0
    env_steps = np.asarray(res.points).astype(int).tolist()
    mean_steps = np.asarray(res.evaluation.mean_steps, np.float64).tolist()
    success = np.asarray(res.evaluation.success_rate, np.float64).tolist()
    # The final evaluation (more episodes, after the last block) replaces the last point.
    mean_steps[-1] = float(final.mean_steps)
    success[-1] = float(final.success_rate)
    return {"env_steps": env_steps, "mean_steps": mean_steps, "success_rate": success,
            "final_steps": float(final.mean_steps), "wall_s": wall, "compile_s": compile_s,
            "episodes": np.asarray(res.episodes).astype(int).tolist(),
            "memory_size": int(np.asarray(res.memory_size)[-1]),
            "memory_flags": int(np.asarray(res.flags)[-1]),
            "hyperparameters": info}


# ------------------------------------------------------------------------------------------
# Sweep (resumable) and summary
# ------------------------------------------------------------------------------------------
def versions() -> Dict[str, str]:
    out = {"python": platform.python_version()}
    for name in ("stable_baselines3", "torch", "gymnasium", "jax", "numpy"):
        try:
            out[name] = __import__(name).__version__
        except ImportError:
            out[name] = "not installed"
    return out


def result_path(out: str, method: str, protocol: str, seed: int) -> str:
    return os.path.join(out, f"{method}__{protocol}__seed{seed}.json")


def _atomic_json(path: str, obj: Any) -> None:
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=1)
    os.replace(tmp, path)


def run_one(method: str, protocol: str, seed: int, steps: Dict[str, int],
            eval_every: Dict[str, int], hedger_episodes: int) -> Dict[str, Any]:
    """One (method, protocol, seed) run: its record (curve, final, wall-clock)."""
    if method in SB3_METHODS:
        rec = run_sb3(method, protocol, seed, steps[method], eval_every[method])
    elif method in METHODS:
        rec = run_hedger(method, protocol, seed, episodes=hedger_episodes)
    else:
        raise ValueError(f"unknown method {method!r}; choose from {METHODS}")
    rec.update(method=method, protocol=protocol, seed=seed,
               first_reach=first_reach(rec["env_steps"], rec["mean_steps"]),
               versions=versions(), machine=machine(), loadavg_end=list(os.getloadavg()))
    return rec


def machine() -> Dict[str, Any]:
    cpu = platform.processor() or "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {"cpu": cpu, "cpu_count": os.cpu_count(), "platform": platform.platform()}


def sweep(methods: Sequence[str], protocols: Sequence[str], seeds: Sequence[int], out: str,
          steps: Dict[str, int], eval_every: Dict[str, int], hedger_episodes: int,
          runner: Callable[..., Dict[str, Any]] = run_one) -> List[str]:
    """Run every missing (method, protocol, seed), method by method; returns the paths
    written. An existing result file is kept (resume); a partial one never exists (atomic
    writes)."""
    os.makedirs(out, exist_ok=True)
    written = []
    for method in methods:
        for protocol in protocols:
            for seed in seeds:
                path = result_path(out, method, protocol, seed)
                if os.path.exists(path):
                    print(f"skip {path} (exists)", flush=True)
                    continue
                load = list(os.getloadavg())
                rec = runner(method, protocol, seed, steps, eval_every, hedger_episodes)
                rec["loadavg_start"] = load
                _atomic_json(path, rec)
                written.append(path)
                reach = rec["first_reach"]
                print(f"{method:>17s} {protocol:>9s} seed {seed}: final "
                      f"{rec['final_steps']:6.1f}  first <= {TARGET:g} at "
                      f"{'never' if reach is None else int(reach)}  "
                      f"({rec['wall_s']:.0f} s)", flush=True)
    return written


def load_results(out: str) -> List[Dict[str, Any]]:
    recs = []
    for name in sorted(os.listdir(out)):
        if name.endswith(".json") and "__seed" in name:
            with open(os.path.join(out, name)) as f:
                recs.append(json.load(f))
    return recs


def _fmt(mean: float, half: float, digits: int = 0) -> str:
    return f"{mean:,.{digits}f} ± {half:,.{digits}f}"


def summarize(recs: List[Dict[str, Any]]) -> Dict[str, Any]:
    """Per (protocol, method): first-reach steps (over the seeds that reached the target),
    final steps-to-goal and wall-clock seconds, each a mean with its 95 % t-interval."""
    rows: Dict[str, Dict[str, Any]] = {}
    for protocol in PROTOCOLS:
        for method in METHODS:
            group = sorted((r for r in recs if r["method"] == method
                            and r["protocol"] == protocol), key=lambda r: r["seed"])
            if not group:
                continue
            reach = [r["first_reach"] for r in group if r["first_reach"] is not None]
            final = np.array([r["final_steps"] for r in group])
            wall = np.array([r["wall_s"] for r in group])
            row = {"n": len(group), "reached": len(reach),
                   "first_reach": [float(v) for v in mean_ci(np.array(reach))] if reach else None,
                   "final": [float(v) for v in mean_ci(final)],
                   "wall_s": [float(v) for v in mean_ci(wall)],
                   "budget_env_steps": float(np.mean([r["env_steps"][-1] for r in group])),
                   "per_seed": [{k: r.get(k) for k in ("seed", "first_reach", "final_steps",
                                                       "wall_s", "compile_s", "env_steps",
                                                       "mean_steps", "success_rate")}
                                for r in group]}
            rows.setdefault(protocol, {})[method] = row
    return rows


def table(rows: Dict[str, Dict[str, Any]], protocol: str) -> str:
    """The Markdown table of one protocol."""
    lines = ["| method | env steps run (mean) | env steps to ≤ 110 (mean ± 95 % CI; seeds reached) "
             "| final steps-to-goal (mean ± 95 % CI) | wall-clock s per run (mean ± 95 % CI) |",
             "|---|---|---|---|---|"]
    for method, row in rows.get(protocol, {}).items():
        if row["first_reach"] is None:
            reach = f"never ({row['reached']}/{row['n']})"
        else:
            reach = f"{_fmt(*row['first_reach'])} ({row['reached']}/{row['n']})"
        lines.append(f"| {method} | {row['budget_env_steps']:,.0f} | {reach} | "
                     f"{_fmt(*row['final'], digits=1)} | {_fmt(*row['wall_s'])} |")
    return "\n".join(lines)


def plot(rows: Dict[str, Dict[str, Any]], path: str,
         references: Optional[Dict[str, Dict[str, float]]] = None) -> None:
    """Steps-to-goal against env steps (log x), mean over seeds with 95 % bands, one line
    per method, one panel per protocol, a dashed line at ``TARGET``; the energy-pumping
    policy's level (``references``) as a grey dotted line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    from experiments.plotting import DPI

    protocols = [p for p in PROTOCOLS if p in rows]
    fig, axes = plt.subplots(1, len(protocols), figsize=(11.0, 5.8), dpi=DPI, sharey=True,
                             squeeze=False)
    colours = dict(zip(METHODS, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    titles = {"gymnasium": "Gymnasium starts: x ~ U[-0.6, -0.4], v = 0",
              "random": "paper's starts: x ~ U[-1.2, 0.5), v ~ U[-0.07, 0.07)"}
    for ax, protocol in zip(axes[0], protocols):
        for method, row in rows[protocol].items():
            seeds = row["per_seed"]
            n_points = min(len(s["env_steps"]) for s in seeds)
            x = np.mean([s["env_steps"][:n_points] for s in seeds], axis=0)
            mean, half = mean_ci(np.array([s["mean_steps"][:n_points] for s in seeds]))
            keep = x > 0                     # the log axis has no 0 (HEDGER's start)
            line, = ax.plot(x[keep], mean[keep], marker="o", ms=2.5, color=colours[method],
                            label=f"{LABELS[method]} (n={row['n']})")
            ax.fill_between(x[keep], (mean - half)[keep], (mean + half)[keep],
                            color=line.get_color(), alpha=0.2)
        ax.axhline(TARGET, color="black", ls="--", lw=1, label=f"{TARGET:g} steps")
        pump = (references or {}).get(protocol, {}).get("energy pumping")
        if pump is not None:
            ax.axhline(pump, color="grey", ls=":", lw=1.2,
                       label=f"push with velocity (hand policy): {pump:.0f}")
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("environment steps (HEDGER: demonstration steps included)")
        ax.set_title(titles[protocol], fontsize=9)
        ax.set_ylim(0, CAP + 5)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2,
                  framealpha=0.9, title="shaded: 95 % interval over seeds", title_fontsize=7)
    axes[0][0].set_ylabel(f"steps to goal (greedy, failures = {CAP})")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def reference_policies(protocol: str, n_episodes: int = FINAL_EPISODES) -> Dict[str, float]:
    """Mean steps to the goal of two hand policies on the final evaluation's episodes:
    pushing in the direction of the velocity (energy pumping; on MountainCar-v0 and on
    MountainCarContinuous-v0 with actions +-1) and uniformly random actions (MountainCar-v0,
    a generator seeded 0)."""
    rng = np.random.default_rng(0)
    return {
        "energy pumping": float(evaluate_steps(
            lambda o: np.where(o[:, 1] >= 0, 2, 0), protocol, n_episodes).mean()),
        "energy pumping, MountainCarContinuous-v0": float(evaluate_steps(
            lambda o: np.where(o[:, 1] >= 0, 1.0, -1.0)[:, None], protocol, n_episodes,
            continuous=True).mean()),
        "random actions": float(evaluate_steps(
            lambda o: rng.integers(0, 3, len(o)), protocol, n_episodes).mean()),
    }


def report(out: str, docs: str) -> Dict[str, Any]:
    """Write ``DOCS/deep_rl.json`` (per-seed numbers) and ``DOCS/deep_rl.png`` from the
    result files in ``out``, and the tables to ``out/deep_rl_tables.md``; print the tables."""
    recs = load_results(out)
    rows = summarize(recs)
    os.makedirs(docs, exist_ok=True)
    runs = {f"{r['method']}/{r['protocol']}/{r['seed']}": r for r in recs}
    references = {p: reference_policies(p) for p in rows}
    blob = {"rows": rows, "runs": runs, "references": references, "target": TARGET, "cap": CAP,
            "eval_episodes": EVAL_EPISODES, "final_episodes": FINAL_EPISODES,
            "eval_seed": EVAL_SEED, "zoo": {k: {kk: str(vv) if isinstance(vv, dict) else vv
                                                 for kk, vv in v.items()}
                                             for k, v in ZOO.items()}}
    _atomic_json(os.path.join(docs, "deep_rl.json"), blob)
    text = "\n\n".join(
        f"### {p}\n\n{table(rows, p)}\n\nreferences (same {FINAL_EPISODES} episodes): "
        + ", ".join(f"{k} {v:.1f}" for k, v in references[p].items())
        for p in PROTOCOLS if p in rows)
    with open(os.path.join(out, "deep_rl_tables.md"), "w") as f:
        f.write(text + "\n")
    print(text)
    if rows:
        plot(rows, os.path.join(docs, "deep_rl.png"), references)
    return rows


def _parse_steps(items: Sequence[str], default: Dict[str, int]) -> Dict[str, int]:
    out = dict(default)
    for item in items:
        name, _, value = item.partition("=")
        if name not in default or not value:
            raise SystemExit(f"--steps/--eval-every: expected METHOD=N with METHOD in "
                             f"{sorted(default)}, got {item!r}")
        out[name] = int(float(value))
    return out


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.deep_rl", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS), choices=METHODS,
                   help=f"methods, run in this order (default: {' '.join(DEFAULT_METHODS)})")
    p.add_argument("--protocols", nargs="+", default=list(PROTOCOLS), choices=PROTOCOLS,
                   help="start protocols (default: gymnasium random)")
    p.add_argument("--seeds", type=int, default=5, help="seeds 0..N-1 (default: 5)")
    p.add_argument("--out", default=os.path.join("results", "deep_rl"),
                   help="directory of the per-run JSON files (default: results/deep_rl)")
    p.add_argument("--docs", default=None,
                   help="where deep_rl.json and deep_rl.png go (default: the --out "
                        "directory; the tables go to OUT/deep_rl_tables.md)")
    p.add_argument("--steps", nargs="*", default=[], metavar="METHOD=N",
                   help="SB3 budgets in env steps (default: "
                        + " ".join(f"{k}={v}" for k, v in BUDGET.items()) + ")")
    p.add_argument("--eval-every", nargs="*", default=[], metavar="METHOD=N",
                   help="SB3 env steps between evaluations (default: "
                        + " ".join(f"{k}={v}" for k, v in EVAL_EVERY.items()) + ")")
    p.add_argument("--hedger-episodes", type=int, default=HEDGER_EPISODES,
                   help=f"HEDGER phase-two episodes, evaluated every {HEDGER_BLOCK} "
                        f"(default: {HEDGER_EPISODES})")
    p.add_argument("--summary-only", action="store_true",
                   help="run nothing: only summarise the result files in --out (default: off)")
    a = p.parse_args(argv)
    steps = _parse_steps(a.steps, BUDGET)
    every = _parse_steps(a.eval_every, EVAL_EVERY)
    if not a.summary_only:
        from hedger_jax import cpu

        cpu.configure()
        try:
            sweep(a.methods, a.protocols, range(a.seeds), a.out, steps, every,
                  a.hedger_episodes)
        except KeyboardInterrupt:
            print("\ninterrupted: finished runs are kept; rerun to resume", file=sys.stderr)
            return 130
    report(a.out, a.docs or a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
