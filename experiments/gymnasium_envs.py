"""HEDGER on Gymnasium's own classic-control envs, through ``Hedger``'s host loop.

``python -m experiments.gymnasium_envs [--seeds 5] [--steps N] [--out DIR]
[--envs MountainCar-v0 Pendulum-v1 ...] [--eval-episodes 20] [--set key=value ...]``

For each env and seed: ``Hedger(env_id, seed=seed, **SETTINGS[env_id].hedger)`` learns for
``steps`` env steps (phase two only: no demonstrations), then its greedy policy is evaluated
on ``eval_episodes`` episodes (``Hedger.evaluate``: each reset with a seed drawn from the
learner's evaluation key, capped by the env's own time limit). A uniformly random policy is
evaluated on as many episodes for reference. Reported per env: mean return and mean episode
length over seeds with 95 % t-intervals (``experiments.stats.mean_ci``), the success rate
(episodes that terminated), stored points, training episodes and wall-clock seconds.
Writes ``DIR/gymnasium_envs.json`` (settings, versions, per-seed numbers, every training
episode's return) and ``DIR/gymnasium_envs.md`` (the table).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time
from typing import Any, Dict, List, Optional

import numpy as np

from experiments.stats import mean_ci

DEFAULT_ENVS = ("MountainCar-v0", "MountainCarContinuous-v0", "Pendulum-v1", "Acrobot-v1")


@dataclasses.dataclass(frozen=True)
class Setting:
    """One env's settings: ``hedger`` (overrides for ``Hedger``: HedgerConfig fields and
    ``action_scale``), ``run`` (RunConfig fields) and the default training budget (steps)."""

    hedger: Dict[str, Any]
    steps: int
    run: Dict[str, Any] = dataclasses.field(default_factory=dict)


#: Chosen per env as docs/gymnasium.md describes (short one-seed pilots). neighbour_index
#: "grid" where the pilots ran faster with it than with "auto"'s choice (results identical).
SETTINGS: Dict[str, Setting] = {
    "MountainCar-v0": Setting(dict(bandwidth=0.02, alpha=0.8, gamma=0.99), 200_000),
    "MountainCarContinuous-v0": Setting(dict(bandwidth=0.03, alpha=0.5, gamma=0.99,
                                             neighbour_index="grid"), 30_000),
    "Pendulum-v1": Setting(dict(bandwidth=0.06, alpha=0.5, gamma=0.95,
                                neighbour_index="grid"), 50_000),
    "Acrobot-v1": Setting(dict(bandwidth=0.25, alpha=0.5, gamma=0.99), 50_000),
}


def _parse_value(text: str) -> Any:
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return {"true": True, "false": False, "none": None}.get(text.lower(), text)


def random_policy(env_id: str, n_episodes: int, seed: int) -> Dict[str, float]:
    """A uniformly random policy on ``n_episodes`` episodes (reset seeds seed, seed+1, ...)."""
    import gymnasium

    env = gymnasium.make(env_id)
    env.action_space.seed(seed)
    lengths, returns = [], []
    for i in range(n_episodes):
        env.reset(seed=seed + i)
        total, n, done = 0.0, 0, False
        while not done:
            _, r, te, tr, _ = env.step(env.action_space.sample())
            total, n, done = total + float(r), n + 1, te or tr
        lengths.append(n)
        returns.append(total)
    return {"mean_return": float(np.mean(returns)), "mean_steps": float(np.mean(lengths))}


def run_seed(env_id: str, setting: Setting, seed: int, steps: int,
             eval_episodes: int) -> Dict[str, Any]:
    """Train one learner and evaluate its greedy policy -> per-seed record."""
    from hedger_jax.agent import RunConfig
    from hedger_jax.learner import Hedger

    t0 = time.time()
    hedger = dict(setting.hedger)
    hedger.setdefault("capacity", steps + 1000)
    probe = Hedger(env_id, capacity=8)
    run = RunConfig(**{"eval_episodes": eval_episodes,
                       "eval_max_steps": probe.env.max_steps, **setting.run})
    model = Hedger(env_id, run_config=run, seed=seed, **hedger)
    returns: List[float] = []
    model.learn(steps, callback=lambda info: returns.extend(map(float, info["returns"])))
    t1 = time.time()
    ev = model.evaluate()
    t2 = time.time()
    return {"seed": seed, "eval": ev, "train_returns": returns,
            "points": int(model.memory.size), "episodes": model.num_episodes,
            "train_seconds": t1 - t0, "eval_seconds": t2 - t1,
            "config": {k: v for k, v in dataclasses.asdict(model.config).items()
                       if k in ("bandwidth", "alpha", "gamma", "capacity", "k_min",
                                "max_neighbours", "input_scale", "input_offset",
                                "neighbour_index")},
            "index": model.config.index_kind}


def summarise(env_id: str, records: List[Dict[str, Any]], baseline: Dict[str, float],
              setting: Setting, steps: int) -> Dict[str, Any]:
    ret = [r["eval"]["mean_return"] for r in records]
    length = [r["eval"]["mean_steps"] for r in records]
    m_r, h_r = mean_ci(ret)
    m_l, h_l = mean_ci(length)
    return {"env": env_id, "hedger": setting.hedger, "run": setting.run, "steps": steps,
            "seeds": [r["seed"] for r in records],
            "mean_return": [float(m_r), float(h_r)], "mean_steps": [float(m_l), float(h_l)],
            "success_rate": float(np.mean([r["eval"]["success_rate"] for r in records])),
            "points": float(np.mean([r["points"] for r in records])),
            "episodes": float(np.mean([r["episodes"] for r in records])),
            "seconds": float(sum(r["train_seconds"] + r["eval_seconds"] for r in records)),
            "random": baseline, "per_seed": records}


def table(rows: List[Dict[str, Any]]) -> str:
    """The markdown table of the summaries."""
    out = ["| env | steps | settings | greedy return | greedy length | success | random return "
           "| random length | seconds |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        h = r["hedger"]
        settings = ", ".join(f"{k}={v}" for k, v in sorted(h.items()))
        out.append(f"| {r['env']} | {r['steps']:,} | {settings} | "
                   f"{r['mean_return'][0]:.1f} ± {r['mean_return'][1]:.1f} | "
                   f"{r['mean_steps'][0]:.1f} ± {r['mean_steps'][1]:.1f} | "
                   f"{r['success_rate']:.2f} | {r['random']['mean_return']:.1f} | "
                   f"{r['random']['mean_steps']:.1f} | {r['seconds']:.0f} |")
    return "\n".join(out) + "\n"


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.gymnasium_envs", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", nargs="+", default=list(DEFAULT_ENVS))
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--steps", type=int, default=None,
                   help="training steps per seed (default: each env's SETTINGS budget)")
    p.add_argument("--eval-episodes", type=int, default=20)
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                   help="override a Hedger setting for every env (e.g. bandwidth=0.05)")
    p.add_argument("--out", default=os.path.join("results", "gymnasium"))
    a = p.parse_args(argv)
    from hedger_jax import cpu

    cpu.configure()
    overrides = dict(kv.split("=", 1) for kv in a.set)
    overrides = {k: _parse_value(v) for k, v in overrides.items()}
    rows, t_all = [], time.time()
    for env_id in a.envs:
        base = SETTINGS.get(env_id, Setting({}, 20_000))
        setting = dataclasses.replace(base, hedger={**base.hedger, **overrides})
        steps = int(a.steps or setting.steps)
        records = []
        for seed in range(a.seeds):
            rec = run_seed(env_id, setting, seed, steps, a.eval_episodes)
            print(f"{env_id} seed {seed}: return {rec['eval']['mean_return']:.1f}, length "
                  f"{rec['eval']['mean_steps']:.1f}, success {rec['eval']['success_rate']:.2f} "
                  f"({rec['episodes']} episodes, {rec['train_seconds']:.0f} s + "
                  f"{rec['eval_seconds']:.0f} s)", flush=True)
            records.append(rec)
        baseline = random_policy(env_id, a.eval_episodes, seed=10_000)
        rows.append(summarise(env_id, records, baseline, setting, steps))
        print(table(rows[-1:]), flush=True)
    import gymnasium
    import jax

    meta = {"versions": {"jax": jax.__version__, "gymnasium": gymnasium.__version__,
                         "numpy": np.__version__, "python": platform.python_version()},
            "machine": {"processor": platform.processor() or platform.machine(),
                        "cpus": os.cpu_count()},
            "seeds": a.seeds, "eval_episodes": a.eval_episodes,
            "total_seconds": time.time() - t_all}
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "gymnasium_envs.json"), "w") as f:
        json.dump({"meta": meta, "rows": rows}, f, indent=1)
    with open(os.path.join(a.out, "gymnasium_envs.md"), "w") as f:
        f.write(table(rows))
    print(table(rows))
    print(f"total {meta['total_seconds']:.0f} s; wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
