"""Two local processes against one process with two host devices, same cores, same sweep.

    python benchmarks/processes.py [--reps 2] [--seeds 8] [--out DIR]

Workload: the README's sweep (Figure-2 quick protocol on discrete mountain car, bandwidths
0.01 0.015 0.02 0.03 0.05 x ``--seeds`` seeds, one ``hedger_jax.sweep`` call). Arms, run
alternately ``--reps`` times, each a fresh set of processes:

* one process with one host device per core (``cpu.configure(host_devices=cores)``);
* ``cores`` processes with one host device each, joined by ``hedger_jax.distributed``
  through ``hedger_jax.launch_local`` (the coordinator on localhost).

Reports each arm's seconds for the ``sweep`` call (trace, compile, run and, across processes,
the gather) and for the whole process (start to exit), the throughput ratio, and whether every
member's numbers are bit-identical between the arms. Writes ``processes.md``/``.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

BANDWIDTHS = (0.01, 0.015, 0.02, 0.03, 0.05)


def worker(out: str, host_devices: int, seeds: int) -> None:
    """One process of an arm: the sweep, timed; process 0 writes ``out`` (JSON)."""
    from hedger_jax import cpu, distributed

    cpu.configure(host_devices=host_devices if host_devices > 1 else None)
    if distributed.detected_cluster():
        distributed.initialize()
    import jax
    import jax.numpy as jnp
    import numpy as np

    import hedger_jax as hj
    from envs.demonstrators import simulated_person_demonstrations
    from envs.mountain_car import MountainCar

    env = MountainCar(continuous=False)
    demos = hj.transitions_from_demonstrations(simulated_person_demonstrations(seed=0))
    run = hj.RunConfig(n_blocks=4, episodes_per_block=50, eval_episodes=200)
    config = hj.HedgerConfig.for_env(env, bandwidth=min(BANDWIDTHS),
                                     max_bandwidth=max(BANDWIDTHS), capacity=45_000)
    train = hj.make_train(env, config, run, phase1=demos).train
    h = jnp.repeat(jnp.array(BANDWIDTHS), seeds)
    params = hj.HedgerParams.create(config, run, bandwidth=h)
    keys = jax.random.split(jax.random.PRNGKey(0), seeds)[jnp.arange(h.size) % seeds]
    t0 = time.perf_counter()
    res = hj.sweep(lambda key, p: train(key, p)[1], keys, params)   # results, not memories
    steps = np.asarray(jax.device_get(res.evaluation.mean_steps))
    sweep_s = time.perf_counter() - t0
    if jax.process_index() == 0:
        with open(out, "w") as f:
            json.dump({"sweep_s": sweep_s, "processes": jax.process_count(),
                       "devices": len(jax.devices()), "mean_steps": steps.tolist()}, f)


def _arm(kind: str, cores: int, seeds: int, tmp: str, rep: int) -> dict:
    from hedger_jax.distributed import launch_local

    out = os.path.join(tmp, f"{kind}-{rep}.json")
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", out, "--seeds", str(seeds)]
    t0 = time.perf_counter()
    if kind == "one process":
        subprocess.run(cmd + ["--host-devices", str(cores)], check=True, cwd=ROOT)
    else:
        launch_local(cmd + ["--host-devices", "1"], cores, log_dir=os.path.join(tmp, kind))
    wall = time.perf_counter() - t0
    with open(out) as f:
        rec = json.load(f)
    rec["process_s"] = wall
    print(kind, {k: v for k, v in rec.items() if k != "mean_steps"}, flush=True)
    return rec


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--out", default=os.path.join("benchmarks", "results"))
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--host-devices", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        return worker(args.worker, args.host_devices, args.seeds)
    import tempfile

    import numpy as np

    cores = os.cpu_count() or 1
    arms = {"one process": [], f"{cores} processes": []}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.reps):
            for kind in arms:
                arms[kind].append(_arm(kind, cores, args.seeds, tmp, rep))
    one, many = arms.values()
    identical = all(np.array_equal(a["mean_steps"], b["mean_steps"]) for a in one for b in many)
    med = lambda rows, k: float(np.median([r[k] for r in rows]))  # noqa: E731
    ratio = med(one, "sweep_s") / med(many, "sweep_s")
    ratio_process = med(one, "process_s") / med(many, "process_s")
    machine = f"{cores} CPU cores, {platform.processor() or platform.machine()}"
    lines = [f"# {cores} local processes against 1 process with {cores} host devices "
             f"({time.strftime('%Y-%m-%dT%H:%M:%S')})", "",
             f"{machine}; the README sweep ({len(BANDWIDTHS)} bandwidths x {args.seeds} seeds, "
             f"Figure-2 quick), {args.reps} alternating repetitions, medians.", "",
             "| arm | sweep call s | whole process s |", "|---|---|---|"]
    for kind, rows in arms.items():
        lines.append(f"| {kind} | {med(rows, 'sweep_s'):.1f} "
                     f"({', '.join('%.1f' % r['sweep_s'] for r in rows)}) | "
                     f"{med(rows, 'process_s'):.1f} |")
    lines += ["", f"Throughput of {cores} processes: **{ratio:.2f}x** one process's (sweep "
              f"call), {ratio_process:.2f}x (whole process). Per-member numbers "
              f"bit-identical: **{identical}**."]
    text = "\n".join(lines) + "\n"
    print(text)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "processes.md"), "w") as f:
        f.write(text)
    with open(os.path.join(args.out, "processes.json"), "w") as f:
        json.dump({"arms": arms, "ratio": ratio, "ratio_process": ratio_process,
                   "identical": identical, "machine": machine}, f, indent=1)


if __name__ == "__main__":
    main()
