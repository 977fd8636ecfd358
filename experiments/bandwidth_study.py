"""Kernel-width study: the paper's fixed bandwidth against data-chosen widths, one program.

``python -m experiments.bandwidth_study [--bandwidths 0.01 0.02 0.05 0.1]
[--methods paper adaptive] [--seeds 5] [--first-seed 0] [--continuous] [--runs 200]
[--eval-episodes 200] [--out results/bandwidth]``

Every (method, initial bandwidth, seed) member runs the Figure-2 protocol (11 simulated-
person demonstrations, then phase-two runs from random starts, greedy evaluations after
phase 1 and after each quarter of the runs) in one compiled program: the methods and the
bandwidths are ``HedgerParams`` settings. Prints steps after phase 1 and after the last run
(mean, 95 % t-interval) per method and bandwidth, and writes ``bandwidth[-continuous].json`` and ``.png`` (the robustness plot).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Any, Dict, List

from hedger_jax.presets import ADAPTIVE, ADAPTIVE_CONTINUOUS

#: Named methods: ``HedgerParams`` settings on top of the initial bandwidth
#: (``action_scale``: the continuous action's factor, 0.5 = from its bounds [-1, 1]).
METHODS: Dict[str, Dict[str, Any]] = {
    "paper": {},
    "adaptive": dict(ADAPTIVE),
    "paper-bounds": {"action_scale": 0.5},
    "adaptive-continuous": dict(ADAPTIVE_CONTINUOUS, action_scale=0.5),
}


def _parse_method(text: str) -> Dict[str, Any]:
    """A method by name (``METHODS``) or as ``name:key=value,key=value``: the named method's
    settings (none for a new name) with those values set."""
    if text in METHODS:
        return dict(METHODS[text])
    name, _, spec = text.partition(":")
    out = dict(METHODS.get(name, {}))
    for item in filter(None, spec.split(",")):
        k, _, v = item.partition("=")
        out[k] = float(v) if "." in v or "e" in v else int(v)
    return out


def run(bandwidths: List[float], methods: List[str], seeds: int, continuous: bool, runs: int,
        eval_episodes: int, capacity: int, seed_mode: str = "map",
        first_seed: int = 0) -> Dict[str, Any]:
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import NamedSharding, PartitionSpec

    from envs.demonstrators import simulated_person_demonstrations
    from envs.mountain_car import MountainCar
    from experiments.figures import MOUNTAIN_CAR, MOUNTAIN_CAR_CONTINUOUS
    from experiments.stats import mean_ci
    from hedger_jax import HedgerConfig, HedgerParams, RunConfig, cpu, make_train
    from hedger_jax.agent import transitions_from_demonstrations
    from hedger_jax.sharding import per_device, seed_mesh

    env = MountainCar(continuous=continuous)
    base = dict(MOUNTAIN_CAR_CONTINUOUS if continuous else MOUNTAIN_CAR)
    base.pop("bandwidth")
    demos = transitions_from_demonstrations(simulated_person_demonstrations(seed=0))
    blocks = 4
    run_cfg = RunConfig(n_blocks=blocks, episodes_per_block=max(1, runs // blocks),
                        eval_episodes=eval_episodes)
    specs = [(m, _parse_method(m)) for m in methods]
    widest = max(h * (float(s.get("kernel_range", 4.0))
                      if s.get("bandwidth_k", 0) else 1.0)
                 for h in bandwidths for _, s in specs)
    config = HedgerConfig.for_env(env, capacity=capacity, bandwidth=min(bandwidths),
                                  max_bandwidth=widest, neighbour_index="grid", **base)
    members = [(m, h, s) for m, _ in specs for h in bandwidths
               for s in range(first_seed, first_seed + seeds)]
    settings: Dict[str, Any] = {}
    for m, spec in specs:
        for h in bandwidths:
            settings[(m, h)] = dict(spec, bandwidth=h)
            if "action_scale" in spec:          # relative to the unit action range's scale
                scale = np.asarray(config.input_scale, np.float64).copy()
                factor = settings[(m, h)].pop("action_scale") / base.get("action_scale", 1.0)
                scale[config.state_dim:] *= factor
                settings[(m, h)]["input_scale"] = scale
    fields = sorted({k for v in settings.values() for k in v})
    defaults = HedgerParams.defaults(config, run_cfg)._asdict()
    values = {k: np.stack([np.asarray(settings[(m, h)].get(k, defaults[k])) for m, h, _ in members])
              for k in fields}
    params = HedgerParams.create(config, run_cfg, **values)
    keys = jnp.stack([jax.random.fold_in(jax.random.PRNGKey(0), s) for _, _, s in members])
    n_dev = len(jax.devices())
    pad = (-len(members)) % n_dev
    if pad:
        keys = jnp.concatenate([keys, jnp.repeat(keys[-1:], pad, 0)])
        params = jax.tree_util.tree_map(lambda x: np.concatenate([x, np.repeat(x[-1:], pad, 0)]),
                                        params)
    mesh = seed_mesh(jax.devices())
    shard = NamedSharding(mesh, PartitionSpec("seeds"))
    train = make_train(env, config, run_cfg, phase1=demos).train
    fn = cpu.jit(per_device(train, mesh, seed_mode), in_shardings=shard, out_shardings=shard)
    t0 = time.perf_counter()
    _, res = jax.block_until_ready(fn(jax.device_put(keys, shard), jax.device_put(params, shard)))
    seconds = time.perf_counter() - t0
    steps = np.asarray(jax.device_get(res.evaluation.mean_steps))[:len(members)]
    points = np.asarray(jax.device_get(res.points))[:len(members)]
    rows = []
    for m, _ in specs:
        for h in bandwidths:
            sel = [i for i, (mm, hh, _) in enumerate(members) if mm == m and hh == h]
            first, last = steps[sel, 0], steps[sel, -1]
            rows.append({"method": m, "bandwidth": h,
                         "after_phase1": [float(x) for x in mean_ci(first)],
                         "final": [float(x) for x in mean_ci(last)],
                         "per_seed_final": last.tolist(),
                         "per_seed_phase1": first.tolist(), "curve": steps[sel].tolist(),
                         "points": float(points[sel, -1].mean())})
            print(f"{m:>12s} h={h:<7g} after phase 1 {rows[-1]['after_phase1'][0]:6.1f} "
                  f"± {rows[-1]['after_phase1'][1]:4.1f}   after {runs} runs "
                  f"{rows[-1]['final'][0]:6.1f} ± {rows[-1]['final'][1]:4.1f}   "
                  f"seeds {np.round(last, 1).tolist()}", flush=True)
    return {"rows": rows, "seconds": seconds, "methods": dict(specs), "continuous": continuous,
            "runs": runs, "seeds": seeds, "first_seed": first_seed,
            "eval_episodes": eval_episodes,
            "config": {"capacity": capacity, "max_bandwidth": widest}}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.bandwidth_study", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bandwidths", nargs="+", type=float, default=[0.01, 0.02, 0.05, 0.1],
                   help="initial bandwidths (default: 0.01 0.02 0.05 0.1)")
    p.add_argument("--methods", nargs="+", default=["paper", "adaptive"],
                   help="methods: names (paper, adaptive, paper-bounds, adaptive-continuous) "
                        "or name:key=value,...: the named method (if any) with "
                        "those HedgerParams fields set (default: paper adaptive)")
    p.add_argument("--seeds", type=int, default=5, help="seeds (default: 5)")
    p.add_argument("--first-seed", type=int, default=0,
                   help="seeds first-seed, first-seed + 1, ... (default: 0)")
    p.add_argument("--continuous", action="store_true", help="continuous actions")
    p.add_argument("--runs", type=int, default=200, help="phase-two runs (default: 200)")
    p.add_argument("--eval-episodes", type=int, default=200,
                   help="evaluation episodes per evaluation (default: 200)")
    p.add_argument("--capacity", type=int, default=45_000, help="memory slots (default: 45000)")
    p.add_argument("--out", default=os.path.join("results", "bandwidth"),
                   help="output directory (default: results/bandwidth)")
    a = p.parse_args(argv)
    from hedger_jax import cpu

    cpu.configure(host_devices=os.cpu_count() if (os.cpu_count() or 1) > 1 else None)
    try:
        out = run(a.bandwidths, a.methods, a.seeds, a.continuous, a.runs, a.eval_episodes,
                  a.capacity, first_seed=a.first_seed)
    except KeyboardInterrupt:
        print("\ninterrupted", file=sys.stderr)
        return 130
    os.makedirs(a.out, exist_ok=True)
    name = os.path.join(a.out, f"bandwidth{'-continuous' if a.continuous else ''}.json")
    with open(name, "w") as f:
        json.dump(out, f, indent=1)
    from experiments.plotting import plot_robustness

    kind = "continuous" if a.continuous else "discrete"
    plot_robustness(name[:-len(".json")] + ".png",
                    f"Robustness to the bandwidth setting\n({kind} mountain car, 11 "
                    f"demonstrations + {a.runs} runs)", out["rows"], {"paper's HEDGER": 56})
    print(f"wrote {name} and its plot ({out['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
