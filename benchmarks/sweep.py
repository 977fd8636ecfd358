"""A hyperparameter sweep as one program against one compile per value, end to end.

    python benchmarks/sweep.py [--values 0.01 ...] [--seeds 8] [--repeats 3] [--out DIR]

Workload: the Figure-2 protocol at ``--quick`` lengths (discrete mountain car, 11 simulated-
person demonstrations, 4 blocks of 50 phase-two runs, 200 evaluation episodes after phase 1
and after each block), a bandwidth sweep of ``--values`` x ``--seeds``. Both arms compile
with ``hedger_jax.jit`` after ``hedger_jax.cpu.configure()`` and run their members one after
another (``lax.map``) on one host device per core, as the experiments CLI does on a CPU:

* one program: ``HedgerConfig(bandwidth=min, max_bandwidth=max)``, the bandwidths as traced
  ``HedgerParams`` -- every (value, seed) member in one compiled program, prepared as
  ``hedger_jax.sweep`` prepares it (``prepare_sweep``: members dealt to the devices in turn,
  the settings they share as constants);
* one compile per value: the static ``HedgerConfig(bandwidth=value)`` per value (what every
  sweep cost before traced params), seeds mapped.

After a small warm-up program (the process's one-time costs), the arms run ``--repeats``
times, alternating which goes first. Reports wall-clock seconds (trace + compile, run, total)
of each arm in each repeat, the median speed-up and compile ratio, the per-value results
of both (mean steps after the last block; they agree to float32 rounding), and the wall time
of the README's sweep block run as it stands in a fresh process (the time the README states
beside it), and writes ``DIR/sweep.md`` and ``DIR/sweep.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


#: The line above the README's sweep block (the line between is its test-tier mark).
README_MARK = "<!-- sweep-snippet: timed by benchmarks/sweep.py -->"


def readme_snippet() -> str:
    """The README's sweep block, as a user would copy it."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with open(os.path.join(root, "README.md"), encoding="utf-8") as f:
        text = f.read()
    start = text.index("```python\n", text.index(README_MARK)) + len("```python\n")
    return text[start:text.index("```", start)]


def readme_snippet_seconds(environ: dict) -> dict:
    """Wall seconds of the README's sweep block in a fresh Python process (start to exit), in
    an empty folder, with ``environ`` (the environment before this script set its XLA flags:
    the block sets its own) and the repository on the path."""
    import subprocess
    import tempfile

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(environ, PYTHONPATH=root + os.pathsep + environ.get("PYTHONPATH", ""))
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-c", readme_snippet()], cwd=tmp, env=env,
                              capture_output=True, text=True)
        wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"the README sweep block failed:\n{proc.stderr[-3000:]}")
    return {"wall_s": wall, "output": proc.stdout.strip()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--values", type=float, nargs="+", default=[0.01, 0.015, 0.02, 0.03, 0.05],
                    help="bandwidths to sweep (default: 0.01 0.015 0.02 0.03 0.05)")
    ap.add_argument("--seeds", type=int, default=8, help="seeds per value (default: 8)")
    ap.add_argument("--index", choices=["grid", "brute", "auto"], default="grid",
                    help="neighbour index of both arms (default: grid; 'auto' picks brute "
                         "force for wide kernels)")
    ap.add_argument("--repeats", type=int, default=3,
                    help="times each arm runs, alternating which goes first; the median "
                         "ratios are reported (default: 3)")
    ap.add_argument("--out", default=os.path.join("benchmarks", "results"),
                    help="output directory (default: benchmarks/results)")
    args = ap.parse_args(argv)
    from hedger_jax import cpu

    n_dev = max(1, os.cpu_count() or 1)
    user_env = dict(os.environ)
    cpu.configure(host_devices=n_dev if n_dev > 1 else None)
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import NamedSharding, PartitionSpec

    from envs.demonstrators import simulated_person_demonstrations
    from envs.mountain_car import MountainCar
    from hedger_jax import HedgerConfig, HedgerParams, RunConfig, make_train
    from hedger_jax.agent import transitions_from_demonstrations
    from hedger_jax.sharding import per_device, prepare_sweep, seed_mesh

    env = MountainCar()
    demos = transitions_from_demonstrations(simulated_person_demonstrations(seed=0))
    run = RunConfig(n_blocks=4, episodes_per_block=50, eval_episodes=200)
    values, S = [float(v) for v in args.values], args.seeds
    mesh = seed_mesh(jax.devices()[:n_dev])
    shard = NamedSharding(mesh, PartitionSpec("seeds"))
    base_keys = jax.random.split(jax.random.PRNGKey(0), S)

    def timed(fn, *xs):
        """(compile seconds, run seconds, output) of a sharded program on inputs xs."""
        t0 = time.perf_counter()
        compiled = cpu.jit(fn, in_shardings=shard, out_shardings=shard).lower(*xs).compile()
        t1 = time.perf_counter()
        out = jax.block_until_ready(compiled(*xs))
        return t1 - t0, time.perf_counter() - t1, out

    def final_steps(results):
        return np.asarray(jax.device_get(results.evaluation.mean_steps))[:, -1]

    def one_program():
        """The one-program arm: every (value, seed) in one compiled program."""
        t_start = time.perf_counter()
        config = HedgerConfig.for_env(env, capacity=45_000, bandwidth=min(values),
                                      max_bandwidth=max(values), neighbour_index=args.index)
        train = make_train(env, config, run, phase1=demos).train
        params = HedgerParams.create(config, run, bandwidth=np.repeat(values, S))
        keys = jnp.tile(base_keys, (len(values), 1))
        # As hj.sweep runs it: members dealt to the devices in turn, shared settings constant.
        fn, members, back = prepare_sweep(train, keys, params, n_dev)
        c, r, (_, res) = timed(per_device(fn, mesh, "map"), *jax.device_put(members, shard))
        return {"compile_s": c, "run_s": r, "total_s": time.perf_counter() - t_start,
                "final": final_steps(res)[back].reshape(len(values), S).mean(1).tolist()}

    def per_value():
        """The baseline arm: one static config, one compile, per value."""
        t_start = time.perf_counter()
        out = {"compile_s": [], "run_s": [], "final": []}
        for h in values:
            cfg = HedgerConfig.for_env(env, capacity=45_000, bandwidth=h,
                                       neighbour_index=args.index)
            train = make_train(env, cfg, run, phase1=demos).train
            c, r, (_, res) = timed(per_device(lambda k: train(k), mesh, "map"),
                                   jax.device_put(base_keys, shard))
            out["compile_s"].append(c)
            out["run_s"].append(r)
            out["final"].append(float(final_steps(res).mean()))
        out["total_s"] = time.perf_counter() - t_start
        return out

    # Warm-up: a small program through the same path first, so that neither arm pays the
    # process's one-time costs (a cold first compile took 28 s where the next took 16 s).
    small = HedgerConfig.for_env(env, capacity=2_000, bandwidth=min(values))
    warm = make_train(env, small, RunConfig(n_blocks=1, episodes_per_block=1,
                                            eval_episodes=2), phase1=demos).train
    timed(per_device(lambda k: warm(k), mesh, "map"), jax.device_put(base_keys, shard))

    # The arms alternate which goes first; each repeat gives one ratio, the median is reported
    # (this VM's compile times vary up to 2x for one and the same program).
    repeats = []
    for i in range(args.repeats):
        arms = {}
        for name in (("one_program", "per_value") if i % 2 == 0 else
                     ("per_value", "one_program")):
            arms[name] = one_program() if name == "one_program" else per_value()
            print(f"repeat {i}", name, arms[name], flush=True)
        repeats.append(arms)
    speedups = [a["per_value"]["total_s"] / a["one_program"]["total_s"] for a in repeats]
    ratios = [a["one_program"]["compile_s"] / float(np.mean(a["per_value"]["compile_s"]))
              for a in repeats]
    mid = int(np.argsort(speedups)[len(speedups) // 2])     # the repeat of the median speed-up
    one, per = repeats[mid]["one_program"], repeats[mid]["per_value"]
    readme = readme_snippet_seconds(user_env)
    print("README snippet", readme, flush=True)
    rows = {"repeats": repeats, "readme_snippet": readme}
    meta = {"index": args.index, "machine": f"{os.cpu_count()} CPU cores, {platform.processor() or platform.machine()}"
                       f", {platform.platform()}", "jax": jax.__version__,
            "devices": len(jax.devices()), "values": values, "seeds": S,
            "date": time.strftime("%Y-%m-%dT%H:%M:%S")}
    speedup, compile_ratio = float(np.median(speedups)), float(np.median(ratios))
    lines = [f"# Bandwidth sweep: one program vs one compile per value ({meta['date']})", "",
             f"{meta['machine']}, jax {meta['jax']}, {meta['devices']} host devices; Figure-2 "
             f"quick protocol (discrete mountain car), bandwidths {values} x {S} seeds, "
             f"neighbour index {args.index}.", "",
             "| repeat (first arm) | one program: compile s, run s, total s | one compile per "
             "value: compile s (each), run s, total s | speed-up | compile ratio |",
             "|---|---|---|---|---|"]
    for i, (a, sp, cr) in enumerate(zip(repeats, speedups, ratios)):
        o, p = a["one_program"], a["per_value"]
        lines.append(f"| {i} ({'one program' if i % 2 == 0 else 'per value'}) | "
                     f"{o['compile_s']:.1f}, {o['run_s']:.1f}, {o['total_s']:.1f} | "
                     f"{sum(p['compile_s']):.1f} ({np.mean(p['compile_s']):.1f}), "
                     f"{sum(p['run_s']):.1f}, {p['total_s']:.1f} | {sp:.2f}x | {cr:.2f}x |")
    lines += ["",
             f"One program is **{speedup:.2f}x** faster end to end (median of {len(repeats)} "
             f"repeats); its compile is **{compile_ratio:.2f}x** a single-setting compile "
             f"(median).", "",
             f"The README's sweep block, run as it stands in a fresh process: "
             f"**{readme['wall_s']:.1f} s** from start to exit.", "",
             "| bandwidth | mean steps after 200 runs, one program | one compile per value |",
             "|---|---|---|"]
    lines += [f"| {h} | {a:.1f} | {b:.1f} |" for h, a, b in zip(values, one["final"], per["final"])]
    text = "\n".join(lines) + "\n"
    print(text)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "sweep.md"), "w") as f:
        f.write(text)
    with open(os.path.join(args.out, "sweep.json"), "w") as f:
        json.dump({"meta": meta, **rows, "speedup": speedup, "compile_ratio": compile_ratio},
                  f, indent=1)


if __name__ == "__main__":
    main()
