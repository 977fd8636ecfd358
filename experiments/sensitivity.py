"""Sensitivity of HEDGER on mountain car to the choices the paper leaves open.

``python -m experiments.sensitivity [--param bandwidth --values 0.01 0.015 0.03 0.1]
[--continuous] [--seeds 3] [--runs 200] [--eval-episodes 300] [--out results/sensitivity]``

Each setting runs the Figure-2 protocol (11 simulated-person demonstrations, then phase-two
runs from random starts) over vmapped seeds and reports the greedy mean steps after phase 1
and after the last phase-two run, with 95% confidence intervals. Settings are static (one
compilation per value), seeds are vmapped.
"""
from __future__ import annotations

import argparse
import os
import time
from typing import Any, Dict, List

from experiments.figures import MOUNTAIN_CAR, MOUNTAIN_CAR_CONTINUOUS, Variant, _items
from experiments.runner import atomic_write_json, run_variant
from experiments.stats import mean_ci
from hedger_jax.agent import RunConfig

PARAMS = ("bandwidth", "k_min", "default_value", "action_scale", "max_neighbours", "gamma")


def sweep(param: str, values: List[Any], *, continuous: bool, seeds: int, runs: int,
          eval_episodes: int, out: str) -> List[Dict[str, Any]]:
    base = dict(MOUNTAIN_CAR_CONTINUOUS if continuous else MOUNTAIN_CAR)
    rows = []
    for value in values:
        hedger = dict(base, capacity=max(45_000, 250 * runs), **{param: value})
        blocks = 4
        variant = Variant(
            label=f"{param}={value}",
            env="mountain_car_continuous" if continuous else "mountain_car_discrete",
            hedger=_items(hedger),
            run=RunConfig(n_blocks=blocks, episodes_per_block=max(1, runs // blocks),
                          eval_episodes=eval_episodes),
            phase1="simulated_person", x_axis="episodes")
        t0 = time.time()
        rec = run_variant(variant, list(range(seeds)), out)
        first = [r[0] for r in rec["mean_steps"]]
        last = [r[-1] for r in rec["mean_steps"]]
        m0, h0 = mean_ci(first)
        m1, h1 = mean_ci(last)
        row = {"param": param, "value": value, "continuous": continuous, "seeds": seeds,
               "after_phase1": [float(m0), float(h0)], "final": [float(m1), float(h1)],
               "curve": [list(map(float, r)) for r in rec["mean_steps"]],
               "points_final": float(sum(p[-1] for p in rec["points"]) / seeds),
               "seconds": time.time() - t0}
        print(f"{param}={value}: after phase 1 {m0:.1f} ± {h0:.1f}, after {runs} runs "
              f"{m1:.1f} ± {h1:.1f} ({row['points_final']:.0f} points)")
        rows.append(row)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.sensitivity", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--param", choices=PARAMS, default="bandwidth")
    p.add_argument("--values", nargs="+", type=float, default=[0.01, 0.015, 0.03, 0.1])
    p.add_argument("--continuous", action="store_true")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--runs", type=int, default=200)
    p.add_argument("--eval-episodes", type=int, default=300)
    p.add_argument("--out", default=os.path.join("results", "sensitivity"))
    a = p.parse_args(argv)
    values = [int(v) if a.param in ("k_min", "max_neighbours") else v for v in a.values]
    rows = sweep(a.param, values, continuous=a.continuous, seeds=a.seeds, runs=a.runs,
                 eval_episodes=a.eval_episodes, out=a.out)
    name = f"{a.param}{'-continuous' if a.continuous else ''}.json"
    atomic_write_json(os.path.join(a.out, name), rows)
    print(f"wrote {os.path.join(a.out, name)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
