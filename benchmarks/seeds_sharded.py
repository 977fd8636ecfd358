"""Seeds over devices: total training points/s of ``hedger_jax.sharding.shard_seeds``.

Run as a script (``hedger_jax.cpu.configure`` forces ``--devices`` host devices before JAX
starts, so it needs a process of its own)::

    python benchmarks/seeds_sharded.py [--devices 2] [--seeds 8] [--capacity 20000] [--out DIR]

Workload: as ``benchmarks/run.py`` (b)/(c): discrete mountain-car episodes (epsilon-greedy
rollout, reverse replay, index refresh) from a memory of ``capacity // 2`` stored points, per
seed. Rows, all in this process: one seed alone; the seeds vmapped, and one after another
(``lax.map``), on one device; ``shard_seeds`` with ``per_device="map"`` and ``"vmap"``; and
the earlier form of ``shard_seeds`` (``jax.jit`` of the vmapped function with the seed axis
sharded by XLA's SPMD partitioner). Rates are wall-clock (the devices run side by side) and per
CPU-second. Writes ``seeds_sharded.md`` and ``.json`` to ``--out``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--capacity", type=int, default=20_000)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--out", default="benchmark_results")
    args = ap.parse_args(argv)
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    from hedger_jax import cpu

    if not cpu.configure(host_devices=args.devices):
        raise SystemExit("run seeds_sharded.py as a script: XLA_FLAGS must be set before JAX")
    import jax
    import numpy as np
    from jax.sharding import NamedSharding, PartitionSpec

    import run as B
    from hedger_jax.sharding import seed_mesh, shard_seeds

    S = args.seeds
    rng = np.random.default_rng(0)
    z, v = B.fake_points(args.capacity // 2, rng)
    cfg = B.mc_config(args.capacity, "grid")
    mem = B.filled_memory(cfg, z, v)
    fn = B.episodes_fn(cfg, False, B.episodes_per_call(cfg, 2))

    def train(key):                      # one seed's work: points trained on
        return fn(mem, key)[1]

    mesh = seed_mesh()
    sharding = NamedSharding(mesh, PartitionSpec("seeds"))
    one_dev = jax.devices()[0]
    spmd = jax.jit(jax.vmap(train), in_shardings=sharding, out_shardings=sharding)
    variants = {
        "one seed": (cpu.jit(train), None),
        "vmap, one device": (cpu.jit(jax.vmap(train)), one_dev),
        "lax.map, one device": (cpu.jit(lambda k: jax.lax.map(train, k)), one_dev),
        "shard_seeds map": (lambda k: shard_seeds(train, k, per_device="map"), None),
        "shard_seeds vmap": (lambda k: shard_seeds(train, k, per_device="vmap"), None),
        "SPMD-sharded vmap (earlier shard_seeds)": (lambda k: spmd(jax.device_put(k, sharding)),
                                                   None),
    }

    def keys(rep, name):
        k = jax.random.fold_in(jax.random.PRNGKey(1), rep)
        if name == "one seed":
            return k
        ks = jax.random.split(k, S)
        return jax.device_put(ks, one_dev) if variants[name][1] is not None else ks

    for name, (f, _) in variants.items():                # compile + warm up
        jax.block_until_ready(f(keys(0, name)))
    rates = {name: [] for name in variants}
    for rep in range(1, args.reps + 1):
        for name, (f, _) in variants.items():
            t0, c0 = time.perf_counter(), time.process_time()
            pts = float(np.sum(np.asarray(jax.block_until_ready(f(keys(rep, name))))))
            rates[name].append((pts / (time.perf_counter() - t0),
                                pts / (time.process_time() - c0)))
    rows = [{"variant": name, "seeds": 1 if name == "one seed" else S,
             "points_per_wall_s": float(np.median([a for a, _ in r])),
             "points_per_cpu_s": float(np.median([b for _, b in r]))}
            for name, r in rates.items()]
    base = rows[0]["points_per_wall_s"]
    for row in rows:
        row["wall_vs_one_seed"] = row["points_per_wall_s"] / base
    meta = {"machine": f"{os.cpu_count()} CPU cores ({B.cpu_model()}), {platform.platform()}",
            "jax": jax.__version__, "devices": len(jax.devices()), "seeds": S,
            "capacity": args.capacity, "stored": args.capacity // 2,
            "XLA_FLAGS": os.environ["XLA_FLAGS"],
            "date": time.strftime("%Y-%m-%dT%H:%M:%S")}
    lines = [f"# Seeds over devices ({meta['date']})", "",
             f"Machine: {meta['machine']}, jax {meta['jax']}, {meta['devices']} forced host "
             f"devices; discrete mountain car, capacity {args.capacity:,}, {args.capacity // 2:,} "
             f"stored points, {S} seeds; medians of {args.reps} calls.", "",
             "| variant | seeds | total points/s (wall) | points per CPU-s | wall vs one seed |",
             "|---|---|---|---|---|"]
    lines += [f"| {r['variant']} | {r['seeds']} | {r['points_per_wall_s']:,.0f} | "
              f"{r['points_per_cpu_s']:,.0f} | {r['wall_vs_one_seed']:.2f} |" for r in rows]
    text = "\n".join(lines) + "\n"
    print(text)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "seeds_sharded.md"), "w") as f:
        f.write(text)
    with open(os.path.join(args.out, "seeds_sharded.json"), "w") as f:
        json.dump({"meta": meta, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
