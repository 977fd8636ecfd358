"""Sensitivity of HEDGER on mountain car to the choices the paper leaves open.

``python -m experiments.sensitivity [--param bandwidth] [--values 0.01 0.015 0.03 0.1]
[--continuous] [--seeds 3] [--runs 200] [--eval-episodes 300] [--out results/sensitivity]``

Each setting runs the Figure-2 protocol (11 simulated-person demonstrations, then phase-two
runs from random starts) over several seeds and reports the greedy mean steps after phase 1
and after the last phase-two run, with 95% confidence intervals. Settings of a traced
parameter (``HedgerParams``: every choice here but ``max_neighbours``) and their seeds run as
one compiled program; ``max_neighbours`` fixes array shapes, so each of its values is a
program of its own.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Any, Dict, List

from experiments.figures import MOUNTAIN_CAR, MOUNTAIN_CAR_CONTINUOUS, Variant, _items
from experiments.runner import atomic_write_json, run_sweep
from experiments.stats import mean_ci
from hedger_jax.agent import RunConfig

#: The settings this CLI sweeps: traced ones (``HedgerParams`` fields, or action_scale,
#: which scales the action's input scale) and static ones (one program per value).
TRACED = ("bandwidth", "k_min", "default_value", "action_scale", "gamma", "alpha",
          "min_weight")
STATIC = ("max_neighbours",)
PARAMS = TRACED + STATIC
#: Each setting's valid range, checked before anything runs: (test, description).
RANGES = {
    "bandwidth": (lambda v: v > 0, "> 0"),
    "k_min": (lambda v: v >= 4 and v == int(v), "an integer >= 4 (dim + 1)"),
    "default_value": (lambda v: True, "any number"),
    "action_scale": (lambda v: v > 0, "> 0"),
    "gamma": (lambda v: 0 <= v <= 1, "in [0, 1]"),
    "alpha": (lambda v: 0 <= v <= 1, "in [0, 1]"),
    "min_weight": (lambda v: 0 < v < 1, "in (0, 1)"),
    "max_neighbours": (lambda v: v >= 4 and v == int(v), "an integer >= 4"),
}


def variants(param: str, values: List[Any], *, continuous: bool, runs: int,
             eval_episodes: int) -> List[Variant]:
    """One Figure-2-protocol variant per value (the value as a traced setting, or in the
    static config for ``STATIC`` settings)."""
    base = dict(MOUNTAIN_CAR_CONTINUOUS if continuous else MOUNTAIN_CAR)
    hedger = dict(base, capacity=max(45_000, 250 * runs))
    blocks = 4
    run = RunConfig(n_blocks=blocks, episodes_per_block=max(1, runs // blocks),
                    eval_episodes=eval_episodes)
    out = []
    for value in values:
        traced = param in TRACED
        out.append(Variant(
            label=f"{param}={value}",
            env="mountain_car_continuous" if continuous else "mountain_car_discrete",
            hedger=_items(hedger if traced else dict(hedger, **{param: value})),
            run=run, phase1="simulated_person", x_axis="episodes",
            params=_items({param: value}) if traced else ()))
    return out


def sweep(param: str, values: List[Any], *, continuous: bool, seeds: int, runs: int,
          eval_episodes: int, out: str, seed_mode: str = "auto",
          devices: Any = 1) -> List[Dict[str, Any]]:
    """Run the sweep (one program for a traced setting) and return a row per value."""
    vs = variants(param, values, continuous=continuous, runs=runs, eval_episodes=eval_episodes)
    groups = [vs] if param in TRACED else [[v] for v in vs]
    t0 = time.time()
    records = [rec for group in groups
               for rec in run_sweep(group, list(range(seeds)), out, seed_batch=None,
                                    seed_mode=seed_mode, devices=devices,
                                    label=f"{param} sweep")]
    seconds = time.time() - t0
    rows = []
    for value, rec in zip(values, records):
        first = [r[0] for r in rec["mean_steps"]]
        last = [r[-1] for r in rec["mean_steps"]]
        m0, h0 = mean_ci(first)
        m1, h1 = mean_ci(last)
        row = {"param": param, "value": value, "continuous": continuous, "seeds": seeds,
               "after_phase1": [float(m0), float(h0)], "final": [float(m1), float(h1)],
               "curve": [list(map(float, r)) for r in rec["mean_steps"]],
               "points_final": float(sum(p[-1] for p in rec["points"]) / seeds),
               "sweep_seconds": seconds}
        print(f"{param}={value}: after phase 1 {m0:.1f} ± {h0:.1f}, after {runs} runs "
              f"{m1:.1f} ± {h1:.1f} ({row['points_final']:.0f} points)")
        rows.append(row)
    print(f"{len(values)} settings x {seeds} seeds in {seconds:.0f} s "
          f"({'one program' if param in TRACED else 'one program per value'})")
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.sensitivity", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--param", choices=PARAMS, default="bandwidth",
                   help="the setting to sweep (default: bandwidth); traced: "
                        f"{', '.join(TRACED)}; static: {', '.join(STATIC)}")
    p.add_argument("--values", nargs="+", type=float, default=[0.01, 0.015, 0.03, 0.1],
                   help="the setting's values (default: 0.01 0.015 0.03 0.1)")
    p.add_argument("--continuous", action="store_true",
                   help="continuous actions (default: discrete)")
    p.add_argument("--seeds", type=int, default=3, help="seeds per value (default: 3)")
    p.add_argument("--runs", type=int, default=200,
                   help="phase-two training runs (default: 200)")
    p.add_argument("--eval-episodes", type=int, default=300,
                   help="greedy evaluation episodes per evaluation (default: 300)")
    p.add_argument("--seed-mode", choices=["auto", "vmap", "map"], default="auto",
                   help="members of the sweep vmapped or one after another (default: auto: "
                        "map on a CPU)")
    p.add_argument("--out", default=os.path.join("results", "sensitivity"),
                   help="output directory (default: results/sensitivity)")
    a = p.parse_args(argv)
    ok, rule = RANGES[a.param]
    bad = [v for v in a.values if not ok(v)]
    if bad:
        p.error(f"--values: {a.param} must be {rule}, got {bad[0]:g}")
    for name in ("seeds", "runs", "eval_episodes"):
        if getattr(a, name) < 1:
            p.error(f"--{name.replace('_', '-')}: must be >= 1")
    from hedger_jax import cpu

    cpu.configure()
    values = [int(v) if a.param in ("k_min", "max_neighbours") else v for v in a.values]
    try:
        rows = sweep(a.param, values, continuous=a.continuous, seeds=a.seeds, runs=a.runs,
                     eval_episodes=a.eval_episodes, out=a.out, seed_mode=a.seed_mode)
    except KeyboardInterrupt:
        print("\ninterrupted — rerun the same command to resume", file=sys.stderr)
        return 130
    name = f"{a.param}{'-continuous' if a.continuous else ''}.json"
    atomic_write_json(os.path.join(a.out, name), rows)
    print(f"wrote {os.path.join(a.out, name)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
