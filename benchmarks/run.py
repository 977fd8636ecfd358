"""hedger-jax benchmarks, all in one process, each speed also as a ratio against a baseline
measured in the same process (the float64 NumPy + cKDTree HEDGER of ``numpy_baseline.py``).

    python benchmarks/run.py [--quick] [--out DIR] [--sections predict,select,train,seeds,compile]

Writes ``DIR/benchmark.md`` (tables) and ``DIR/benchmark.json`` (default DIR:
``benchmarks/results``). Sections:

  predict  batched Algorithm-1 predictions/s at capacities 1e3..1e6 (brute force and grid
           index) vs the baseline (cKDTree query + per-query float64 LWR/IVH);
  select   batched neighbour selection: grid index vs ``cKDTree.query`` on the same points
           and queries (k = max_neighbours, distance_upper_bound = k_thresh);
  train    training points/s on mountain-car episodes (epsilon-greedy rollout + reverse
           replay, index refreshed per episode), discrete and continuous, vs the baseline;
  seeds    total training points/s vs the number of vmapped seeds;
  compile  jit compile time of a full ``make_train(...).train``;
  and the peak resident memory (``resource.getrusage`` maxrss) after each section.

Data: mountain-car-like scaled inputs (state uniform in [0, 1]^2, action in {-1, 0, 1} or,
continuous, uniform in [-1, 1] times ``CONTINUOUS_ACTION_SCALE``), the library's default
bandwidth 0.015 (k_thresh 0.032) and max_neighbours 32: the settings the experiments and
``Hedger``'s presets use for mountain car.
"""
from __future__ import annotations

import argparse
import datetime
import functools
import json
import os
import platform
import resource
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from envs.mountain_car import MountainCar  # noqa: E402
from hedger_jax.agent import (RunConfig, make_train, rollout, train_prefix,  # noqa: E402
                              training_act)
from hedger_jax.config import HedgerConfig  # noqa: E402
from hedger_jax.memory import init_memory, refresh_index, select_neighbours  # noqa: E402
from hedger_jax.index import geometry, merge_threshold  # noqa: E402
from hedger_jax.prediction import predict_scaled  # noqa: E402
from hedger_jax.data_bandwidth import with_data_bandwidth  # noqa: E402
import hedger_jax  # noqa: E402
from hedger_jax import cpu as hj_cpu  # noqa: E402
from numpy_baseline import NumpyHedger, time_episodes  # noqa: E402

DISCRETE = ((-1.0,), (0.0,), (1.0,))


def cpu_model() -> str:
    """The CPU's model name and family from /proc/cpuinfo (Linux), else platform's guess."""
    try:
        with open("/proc/cpuinfo") as fh:
            info = dict(line.split(":", 1) for line in fh.read().split("\n\n")[0].splitlines()
                        if ":" in line)
        info = {k.strip(): v.strip() for k, v in info.items()}
        return f"{info.get('model name', '?')} (family {info.get('cpu family', '?')}, " \
               f"model {info.get('model', '?')})"
    except OSError:
        return platform.processor() or "unknown"


def maxrss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def timeit(fn, min_time=0.5, max_reps=50):
    """(wall seconds, process CPU seconds) per call of fn() (blocking), after a warm-up call.

    CPU seconds (all threads of this process) are the per-core measure: on a shared, loaded
    machine the wall time also counts the time other processes held the cores.
    """
    jax.block_until_ready(fn())
    n, t0, c0 = 0, time.perf_counter(), time.process_time()
    while True:
        jax.block_until_ready(fn())
        n += 1
        dt = time.perf_counter() - t0
        if dt >= min_time or n >= max_reps:
            return dt / n, (time.process_time() - c0) / n


def paired_rounds(fns, rounds=15, calls=3):
    """Interleaved timing of several callables (blocking) in one process: ``rounds`` rounds,
    each timing ``calls`` calls of every callable in turn (order reversed every other
    round), each block after an untimed call. -> {name: (CPU seconds per call per round
    (list), wall seconds per call per round (list))}. Ratios of the same round compare
    programs run seconds apart, so they are robust to the machine's speed drifting (on the
    2-core VM the same program ran 20-30 % faster or slower from one minute or hour to the
    next). The untimed call refills the caches the other programs evicted: without it, the
    10^4-slot predictions, timed right after the 3e5-slot ones, ran ~10 % slower than in a
    loop of their own (ratio 2.65x instead of 2.91x, measured)."""
    for fn in fns.values():
        jax.block_until_ready(fn())
    cpu = {k: [] for k in fns}
    wall = {k: [] for k in fns}
    names = list(fns)
    for r in range(rounds):
        for k in (names if r % 2 == 0 else names[::-1]):
            jax.block_until_ready(fns[k]())
            t0, c0 = time.perf_counter(), time.process_time()
            for _ in range(calls):
                jax.block_until_ready(fns[k]())
            cpu[k].append((time.process_time() - c0) / calls)
            wall[k].append((time.perf_counter() - t0) / calls)
    return {k: (cpu[k], wall[k]) for k in fns}


def ratio_stats(num, den):
    """Median and quartiles of the per-round ratios num[i] / den[i]."""
    r = np.asarray(num, float) / np.asarray(den, float)
    q25, med, q75 = np.percentile(r, [25, 50, 75])
    return {"median": float(med), "q25": float(q25), "q75": float(q75), "rounds": len(r)}


#: Scaled action = action x this for continuous mountain car: the experiments' and the
#: ``Hedger`` preset's setting (``experiments.figures.MOUNTAIN_CAR_CONTINUOUS``,
#: ``hedger_jax.learner.ENV_PRESETS``). (Benchmarks before 2026-12-02 used raw actions,
#: 1.0, which no shipped configuration uses: 10x sparser neighbourhoods in the action.)
CONTINUOUS_ACTION_SCALE = 0.1


def mc_config(capacity, kind, continuous=False, **kw):
    env = MountainCar(continuous=continuous)
    if continuous:
        kw.setdefault("action_scale", CONTINUOUS_ACTION_SCALE)
    return HedgerConfig.for_env(env, capacity=capacity, neighbour_index=kind, **kw)


def fake_points(n, rng, continuous=False, action_scale=CONTINUOUS_ACTION_SCALE):
    """(n, 3) scaled mountain-car-like inputs and small positive values (continuous actions
    uniform in [-1, 1], scaled by ``action_scale`` as ``mc_config`` does)."""
    z = np.empty((n, 3), np.float32)
    z[:, :2] = rng.uniform(0, 1, (n, 2))
    z[:, 2] = (rng.uniform(-1, 1, n) * action_scale) if continuous \
        else rng.integers(-1, 2, n)
    return z, rng.uniform(0, 1e-2, n).astype(np.float32)


def filled_memory(cfg, z, v):
    n = z.shape[0]
    pts = np.zeros((cfg.dim, cfg.capacity), np.float32)
    pts[:, :n] = z.T
    vals = np.zeros(cfg.capacity, np.float32)
    vals[:n] = v
    m = init_memory(cfg)._replace(points=jnp.asarray(pts), values=jnp.asarray(vals),
                                  size=jnp.int32(n), head=jnp.int32(n % cfg.capacity))
    if m.index is not None:
        m = jax.jit(functools.partial(refresh_index, cfg))(m._replace(index=None))
    return m


def baseline_agent(cfg, z, v):
    ag = NumpyHedger(dim=cfg.dim, capacity=cfg.capacity, bandwidth=cfg.bandwidth,
                     max_neighbours=cfg.max_neighbours, k_min=cfg.k_min, alpha=cfg.alpha,
                     gamma=cfg.gamma, offset=cfg.input_offset, scale=cfg.input_scale,
                     discrete_actions=cfg.discrete_actions, action_low=cfg.action_low[0],
                     action_high=cfg.action_high[0])
    n = z.shape[0]
    ag.points[:n] = z
    ag.values[:n] = v
    ag.size = n
    ag.refresh()
    return ag


# ---------------------------------------------------------------------- sections
def bench_predict(caps, batch, rng, results, scaling=(10_000, 300_000)):
    rows = []
    queries, _ = fake_points(batch, rng)
    q = jnp.asarray(queries)
    kept = {}                  # the grid programs of the capacity-scaling pair, kept for the end
    for cap in caps:
        z, v = fake_points(cap, rng)
        row = {"capacity": cap}
        for kind in ("brute", "grid"):
            if kind == "brute" and cap > 300_000:
                continue
            cfg = mc_config(cap, kind)
            mem = filled_memory(cfg, z, v)
            nq = batch if kind == "grid" or cap <= 10_000 else max(64, batch * 10_000 // cap)
            f = jax.jit(jax.vmap(lambda m, zz, cfg=cfg: predict_scaled(cfg, m, zz).value,
                                 (None, 0)))
            dt, ct = timeit(lambda: f(mem, q[:nq]))
            row[f"{kind}_per_s"] = nq / ct
            row[f"{kind}_per_wall_s"] = nq / dt
            if kind == "grid":
                row["mean_neighbours"] = float(jnp.mean(jax.jit(jax.vmap(
                    lambda zz: select_neighbours(cfg, mem, zz).mask.sum()))(q[:256])))
                if cap in scaling:
                    kept[cap] = functools.partial(f, mem, q)
            del mem
        cfg = mc_config(cap, "brute")
        ag = baseline_agent(cfg, z.astype(np.float64), v.astype(np.float64))
        nb, q64 = 200, queries.astype(np.float64)
        ag.predict_scaled(q64[:nb])                              # warm-up
        t0, c0, done = time.perf_counter(), time.process_time(), 0
        while time.process_time() - c0 < 0.5 or done < nb:      # >= 0.5 CPU-s, >= 200 queries
            start = (done // nb) % (batch // nb) * nb            # whole slices of nb queries
            ag.predict_scaled(q64[start:start + nb])
            done += nb
        row["baseline_per_s"] = done / (time.process_time() - c0)
        row["baseline_per_wall_s"] = done / (time.perf_counter() - t0)
        for kind in ("brute", "grid"):
            if f"{kind}_per_s" in row:
                row[f"{kind}_ratio"] = row[f"{kind}_per_s"] / row["baseline_per_s"]
        rows.append(row)
        print("predict", row, flush=True)
    results["predict"] = rows
    if len(kept) == 2:
        # Cost at the large capacity over the cost at the small one, the same batch of
        # queries, timed in interleaved rounds (``paired_rounds``): the table's rates were
        # measured minutes apart.
        small, large = sorted(kept)
        t = paired_rounds({"small": kept[small], "large": kept[large]})
        results["predict_scaling"] = dict(
            small=small, large=large, batch=batch, **ratio_stats(t["large"][0], t["small"][0]),
            wall=ratio_stats(t["large"][1], t["small"][1]))
        print("predict scaling", results["predict_scaling"], flush=True)


def bench_select(caps, batch, rng, results):
    rows = []
    queries, _ = fake_points(batch, rng)
    q = jnp.asarray(queries)
    for cap in caps:
        z, v = fake_points(cap, rng)
        cfg = mc_config(cap, "grid")
        t0 = time.perf_counter()
        mem = filled_memory(cfg, z, v)
        jax.block_until_ready(mem)
        f = jax.jit(jax.vmap(lambda m, zz: select_neighbours(cfg, m, zz), (None, 0)))
        t0 = time.perf_counter()
        tree = cKDTree(z)
        t_tree = time.perf_counter() - t0

        def kd(workers):
            return lambda: tree.query(queries, k=cfg.max_neighbours,
                                      distance_upper_bound=cfg.k_thresh, workers=workers)

        # The grid and cKDTree in interleaved rounds (``paired_rounds``); rates are medians
        # over the rounds, ratios the medians of the rounds' ratios.
        t = paired_rounds({"grid": lambda: f(mem, q), "w1": kd(1), "w-1": kd(-1)},
                          rounds=9 if batch < 4096 else 15)
        row = {"capacity": cap, "grid_per_s": batch / np.median(t["grid"][0]),
               "grid_per_wall_s": batch / np.median(t["grid"][1]), "kdtree_build_s": t_tree}
        for workers in ("1", "-1"):
            cpu, wall = t["w" + workers]
            row[f"kdtree_w{workers}_per_s"] = batch / np.median(cpu)
            row[f"kdtree_w{workers}_per_wall_s"] = batch / np.median(wall)
            stats = ratio_stats(cpu, t["grid"][0])
            name = "w1" if workers == "1" else "all"
            row[f"ratio_vs_kdtree_{name}"] = stats["median"]
            row[f"ratio_vs_kdtree_{name}_quartiles"] = [stats["q25"], stats["q75"]]
            row[f"wall_ratio_vs_kdtree_{name}"] = ratio_stats(wall, t["grid"][1])["median"]
        # exactness spot check against cKDTree (distances; ties aside)
        out = f(mem, q[:256])
        dk, _ = tree.query(queries[:256], k=cfg.max_neighbours, distance_upper_bound=cfg.k_thresh)
        cnt_k = np.isfinite(dk).sum(1)
        row["counts_match_kdtree"] = float(np.mean(np.asarray(out.mask.sum(1)) == cnt_k))
        # merge-refresh cost after one episode of new points
        m2 = mem._replace(index=mem.index._replace(n_new=jnp.int32(min(200, cap))))
        rf = jax.jit(functools.partial(refresh_index, cfg))
        row["refresh_200_new_s"] = timeit(lambda: rf(m2), min_time=0.3, max_reps=5)[1]
        rows.append(row)
        print("select", row, flush=True)
        del mem, m2
    results["select"] = rows


def episodes_fn(cfg, continuous, n_episodes):
    env = MountainCar(continuous=continuous)
    params = env.default_params()
    run = RunConfig()

    def one(memory, key):            # as the agent's episodes: the index refreshed after each
        k1, k2 = jax.random.split(key)
        obs0, s0 = env.reset(k1, params)

        hp = with_data_bandwidth(cfg, memory, None)     # as make_train: once per episode
        out = rollout(env, params, training_act(cfg, run, memory, params=hp), k2,
                      env.max_steps, obs0, s0)
        ep, length = out[0], out[1]
        return refresh_index(cfg, train_prefix(cfg, memory, ep, length, *out[2:],
                                               params=hp)), length

    def run_eps(memory, key):
        memory, lengths = jax.lax.scan(one, memory, jax.random.split(key, n_episodes))
        return memory, jnp.sum(lengths)

    return run_eps


def episodes_per_call(cfg, minimum: int) -> int:
    """Episodes per timed training call: at least ``minimum`` and, with the grid index, two
    merge periods (a call starts from a memory with nothing pending; 200-step episodes merge
    after every ceil(merge_threshold / 200) episodes), so that every call pays the merges of
    the writes it makes, as a long run does (with fewer episodes a call could end before its
    first merge and time none)."""
    if cfg.index_kind != "grid":
        return minimum
    per_merge = -(-merge_threshold(geometry(cfg).recent) // MountainCar().max_steps)
    return max(minimum, 2 * per_merge)


class InterleavedBaseline:
    """The NumPy/cKDTree baseline's episodes, one per call of ``step``, from ``agent`` (which
    learns as it goes: episode i uses seed i, so every run does the same work), timed so
    that ``time_training`` can alternate them with the JAX calls it times: both then see
    the same minutes of this VM, whose speed drifts (the baseline's rate moved 207-297
    points/s between runs an hour apart)."""

    def __init__(self, agent, continuous, min_cpu, min_episodes):
        self.agent, self.continuous = agent, continuous
        self.min_cpu, self.min_episodes = min_cpu, min_episodes
        self.points = self.cpu = self.wall = 0.0
        self.episodes = 0

    def done(self):
        return self.episodes >= self.min_episodes and self.cpu >= self.min_cpu

    def step(self):
        c0 = time.process_time()
        p, t = time_episodes(self.agent, 1, seed=self.episodes, continuous=self.continuous)
        self.cpu += time.process_time() - c0
        self.points, self.wall, self.episodes = self.points + p, self.wall + t, self.episodes + 1


class InterleavedCalls:
    """A second configuration's timed training calls, one per ``step``, each from a fresh copy
    of ``mem``, so that ``time_training`` can alternate them with the calls it times: the
    ratio of the two rates then compares the same minutes of this VM (timed apart, the
    adaptive/grid ratio read 0.39-0.75 for one program across runs minutes apart)."""

    def __init__(self, cfg, continuous, mem, n_episodes, min_cpu):
        self.f = hj_cpu.jit(episodes_fn(cfg, continuous, n_episodes), donate_argnums=(0,))
        self.mem, self.min_cpu = mem, min_cpu
        self.points = self.cpu = self.wall = 0.0
        self.calls = 0
        t0 = time.perf_counter()
        jax.block_until_ready(self.f(self._fresh(), jax.random.PRNGKey(0)))  # compile + warm-up
        self.first_call_s = time.perf_counter() - t0

    def _fresh(self):
        return jax.block_until_ready(jax.tree_util.tree_map(jnp.copy, self.mem))

    def done(self):
        return self.calls >= 1 and self.cpu >= self.min_cpu

    def step(self):
        m = self._fresh()
        key = jax.random.fold_in(jax.random.PRNGKey(1), self.calls + 1)
        t0, c0 = time.perf_counter(), time.process_time()
        _, pts = jax.block_until_ready(self.f(m, key))
        self.wall, self.cpu = self.wall + time.perf_counter() - t0, \
            self.cpu + time.process_time() - c0
        self.points += float(np.sum(np.asarray(pts)))
        self.calls += 1


def time_training(cfg, continuous, mem, n_episodes, n_seeds=None, min_cpu=2.0,
                  max_reps=40, seed_mode="vmap", partners=()):
    """(points per CPU-second, first-call seconds, points per wall-second). ``seed_mode``:
    with ``n_seeds``, "vmap" (the seeds batched) or "map" (``lax.map``: one after another in
    the same program, as ``shard_seeds`` runs a CPU device's seeds).

    Each timed call runs ``n_episodes`` from a fresh copy of ``mem`` (copied outside the
    timing) with its own key, repeated until ``min_cpu`` CPU-seconds (or ``max_reps`` calls).
    ``partners`` (``InterleavedBaseline`` or ``InterleavedCalls``): one step of each after
    each timed call, until all have their minimum (then the calls go on past ``max_reps`` if
    a partner needs it), so all are timed over the same minutes.
    """
    fn = episodes_fn(cfg, continuous, n_episodes)
    if n_seeds is not None and seed_mode == "map":
        one = fn
        fn = lambda m, k: jax.lax.map(lambda a: one(*a), (m, k))  # noqa: E731
    elif n_seeds is not None:
        fn = jax.vmap(fn)
    f = hj_cpu.jit(fn, donate_argnums=(0,))
    fresh = lambda: jax.block_until_ready(jax.tree_util.tree_map(jnp.copy, mem))  # noqa: E731

    def keys(rep):
        key = jax.random.fold_in(jax.random.PRNGKey(1), rep)
        return key if n_seeds is None else jax.random.split(key, n_seeds)

    m = fresh()
    t0 = time.perf_counter()
    jax.block_until_ready(f(m, keys(0)))                         # compile + warm-up
    t_first = time.perf_counter() - t0
    n = wall = cpu = 0.0
    rep = 0
    while (cpu < min_cpu and rep < max_reps) or rep == 0 or \
            not all(p.done() for p in partners):
        rep += 1
        m = fresh()
        t0, c0 = time.perf_counter(), time.process_time()
        _, pts = jax.block_until_ready(f(m, keys(rep)))
        wall, cpu = wall + time.perf_counter() - t0, cpu + time.process_time() - c0
        n += float(np.sum(np.asarray(pts)))
        for p in partners:
            if not p.done():
                p.step()
    return n / cpu, t_first, n / wall


def bench_train(settings, rng, results, quick):
    rows = []
    for continuous, cap, prefill in settings:
        z, v = fake_points(prefill, rng, continuous)
        row = {"actions": "continuous" if continuous else "discrete", "capacity": cap,
               "prefill": prefill}
        # The baseline's episodes alternate with the calls of the last (headline) column.
        base = InterleavedBaseline(
            baseline_agent(mc_config(cap, "brute", continuous), z.astype(np.float64),
                           v.astype(np.float64)),
            continuous, min_cpu=0.5 if quick else 2.0, min_episodes=1 if quick else 2)
        # "adaptive": the grid with the beyond-the-paper option, at 2e4 slots only: discrete
        # hedger_jax.ADAPTIVE (the width read from the memory once per rollout and once per
        # replay), continuous hedger_jax.ADAPTIVE_CONTINUOUS; its calls alternate with the
        # grid column's too, so adaptive / grid compares the same minutes.
        partners = [base]
        if cap <= 20_000:
            preset = hedger_jax.ADAPTIVE_CONTINUOUS if continuous else hedger_jax.ADAPTIVE
            cfg = mc_config(cap, "grid", continuous, **preset)
            n_eps = episodes_per_call(cfg, 2 if quick else 4)
            adaptive = InterleavedCalls(cfg, continuous, filled_memory(cfg, z, v), n_eps,
                                        min_cpu=0.5 if quick else 2.0)
            partners.append(adaptive)
            row["adaptive_episodes_per_call"] = n_eps
            row["adaptive_first_call_s"] = adaptive.first_call_s
        for kind in ("brute", "grid"):
            if kind == "brute" and cap > 100_000:
                continue
            cfg = mc_config(cap, kind, continuous)
            n_eps = episodes_per_call(cfg, 2 if quick else 4)
            row[f"{kind}_episodes_per_call"] = n_eps
            pps, t_first, wall = time_training(
                cfg, continuous, filled_memory(cfg, z, v), n_eps,
                min_cpu=0.5 if quick else 2.0, partners=partners if kind == "grid" else ())
            row[f"{kind}_points_per_s"] = pps
            row[f"{kind}_points_per_wall_s"] = wall
            row[f"{kind}_first_call_s"] = t_first
        if len(partners) > 1:
            row["adaptive_points_per_s"] = adaptive.points / adaptive.cpu
            row["adaptive_points_per_wall_s"] = adaptive.points / adaptive.wall
        row["baseline_points_per_s"] = base.points / base.cpu
        row["baseline_points_per_wall_s"] = base.points / base.wall
        row["baseline_episodes"] = base.episodes
        if "adaptive_points_per_s" in row:
            row["adaptive_vs_grid"] = row["adaptive_points_per_s"] / row["grid_points_per_s"]
        for kind in ("brute", "grid", "adaptive"):
            if f"{kind}_points_per_s" in row:
                row[f"{kind}_ratio"] = row[f"{kind}_points_per_s"] / row["baseline_points_per_s"]
        rows.append(row)
        print("train", row, flush=True)
    results["train"] = rows


def bench_seeds(seed_counts, cap, prefill, rng, results, quick, kind, baseline_pps=None):
    rows = []
    z, v = fake_points(prefill, rng)
    cfg = mc_config(cap, kind)
    base = None
    # The grid also with the seeds one after another in one program (lax.map), as
    # hedger_jax.sharding.shard_seeds runs a CPU device's seeds.
    for mode in ("vmap", "map") if kind == "grid" else ("vmap",):
        for n in seed_counts:
            mem = filled_memory(cfg, z, v)
            mems = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (n,) + x.shape).copy(),
                                          mem)
            del mem
            n_eps = episodes_per_call(cfg, 1 if quick else 2)
            pps, t_first, wall = time_training(cfg, False, mems, n_eps, n_seeds=n,
                                               min_cpu=0.5 if quick else 2.0, seed_mode=mode)
            base = base or pps
            rows.append({"seeds": n, "index": kind, "mode": mode, "capacity": cap,
                         "prefill": prefill, "total_points_per_s": pps,
                         "total_points_per_wall_s": wall, "per_seed_points_per_s": pps / n,
                         "speedup_vs_1_seed": pps / base,
                         "ratio_vs_baseline": (pps / baseline_pps) if baseline_pps else None})
            print("seeds", rows[-1], flush=True)
            del mems
    results.setdefault("seeds", []).extend(rows)


def bench_compile(results):
    rows = []
    run = RunConfig(n_blocks=2, episodes_per_block=2, eval_episodes=16)
    for continuous, kind in ((False, "brute"), (False, "grid"), (True, "brute"), (True, "grid")):
        env = MountainCar(continuous=continuous)
        cfg = mc_config(20_000, kind, continuous)
        train = make_train(env, cfg, run).train
        t0 = time.perf_counter()
        lowered = jax.jit(train).lower(jax.random.PRNGKey(0))
        t_lower = time.perf_counter() - t0
        t0, c0 = time.perf_counter(), time.process_time()
        lowered.compile()
        t_comp, c_comp = time.perf_counter() - t0, time.process_time() - c0
        rows.append({"actions": "continuous" if continuous else "discrete", "index": kind,
                     "trace_lower_s": t_lower, "compile_s": t_comp, "compile_cpu_s": c_comp,
                     "total_s": t_lower + t_comp})
        print("compile", rows[-1], flush=True)
    results["compile"] = rows


# ---------------------------------------------------------------------- report
def fmt(x, nd=0):
    if x is None:
        return "-"
    if isinstance(x, float):
        return f"{x:,.{nd}f}"
    return str(x)


def markdown(results) -> str:
    m = results["machine"]
    out = [f"# hedger-jax benchmarks ({results['date']})", "",
           f"Machine: {m['cpu_count']} CPU cores ({m.get('cpu', 'CPU not recorded')}), "
           f"{m['platform']}, jax {m['jax']} "
           f"({m['backend']}), load average at start {m['load_start']}, at end "
           f"{m.get('load_end', '-')}. Mode: {'quick' if results['quick'] else 'full'}. "
           f"`hedger_jax.cpu.configure()` called: {m.get('configured', 'not recorded')}; "
           f"XLA_FLAGS: `{m.get('xla_flags', 'not recorded')}`.", "",
           "Baseline = float64 NumPy + scipy cKDTree HEDGER in the same process "
           "(benchmarks/numpy_baseline.py, single-threaded). Ratio = ours / baseline. "
           "Rates are per CPU-second of this process (time.process_time, all threads: the "
           "per-core measure, robust to other processes' load); wall-clock rates are in the JSON "
           "(`*_per_wall_s`) and, for training, in the tables.", ""]
    if "predict" in results:
        out += ["## (a) Batched predictions/s (Algorithm 1)", "",
                "| capacity | brute /s | grid /s | mean neighbours | baseline /s | brute ratio | "
                "grid ratio |", "|---|---|---|---|---|---|---|"]
        for r in results["predict"]:
            out.append(f"| {r['capacity']:,} | {fmt(r.get('brute_per_s'))} | "
                       f"{fmt(r.get('grid_per_s'))} | {fmt(r.get('mean_neighbours'), 1)} | "
                       f"{fmt(r['baseline_per_s'])} | {fmt(r.get('brute_ratio'), 1)} | "
                       f"{fmt(r.get('grid_ratio'), 1)} |")
        out.append("")
        sc = results.get("predict_scaling")
        if sc:
            out += [f"Grid prediction cost at {sc['large']:,} slots over the cost at "
                    f"{sc['small']:,}, the same {sc['batch']}-query batch, timed in {sc['rounds']} "
                    f"interleaved rounds (per CPU-second): **{sc['median']:.2f}x** (quartiles "
                    f"{sc['q25']:.2f}-{sc['q75']:.2f}; wall-clock {sc['wall']['median']:.2f}x). "
                    "The rates above were measured minutes apart.", ""]
    if "select" in results:
        out += ["## Batched neighbour selection: grid index vs cKDTree.query (same points, "
                "same queries)", "",
                "The grid and cKDTree timed in interleaved rounds; rates are the rounds' "
                "medians, ratios the medians of the rounds' ratios (quartiles in brackets; "
                "wall-clock ratios in the JSON).", "",
                "| capacity | grid /s | cKDTree 1 worker /s | cKDTree all cores /s | ratio vs 1 "
                "worker | ratio vs all | tree build s | grid refresh (200 new) s | counts match |",
                "|---|---|---|---|---|---|---|---|---|"]

        def quart(r, name):
            q = r.get(f"ratio_vs_kdtree_{name}_quartiles")
            return f" ({q[0]:.2f}-{q[1]:.2f})" if q else ""

        for r in results["select"]:
            out.append(f"| {r['capacity']:,} | {fmt(r['grid_per_s'])} | "
                       f"{fmt(r['kdtree_w1_per_s'])} | {fmt(r['kdtree_w-1_per_s'])} | "
                       f"{fmt(r['ratio_vs_kdtree_w1'], 2)}{quart(r, 'w1')} | "
                       f"{fmt(r['ratio_vs_kdtree_all'], 2)}{quart(r, 'all')} | "
                       f"{fmt(r['kdtree_build_s'], 3)} | {fmt(r['refresh_200_new_s'], 4)} | "
                       f"{fmt(r['counts_match_kdtree'], 3)} |")
        out.append("")
    if "train" in results:
        out += ["## (b) Training points/s, mountain car (epsilon-greedy episodes + reverse "
                "replay, one seed)", "",
                "Each timed call runs episodes from the same stored points (the grid's: two "
                "merge periods of its recent list per call, `episodes_per_call`, so the index "
                "merges are paid as in a long run). The baseline's episodes and the adaptive "
                "column's calls alternate with the grid column's calls (one of each after "
                "each), so all three are timed over the same minutes.", "",
                "| actions | capacity | stored points | brute /s | grid /s | grid /s wall | "
                "baseline /s | brute ratio | grid ratio | adaptive /s | adaptive / grid |",
                "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in results["train"]:
            out.append(f"| {r['actions']} | {r['capacity']:,} | {r['prefill']:,} | "
                       f"{fmt(r.get('brute_points_per_s'))} | {fmt(r.get('grid_points_per_s'))} | "
                       f"{fmt(r.get('grid_points_per_wall_s'))} | "
                       f"{fmt(r['baseline_points_per_s'])} | {fmt(r.get('brute_ratio'), 1)} | "
                       f"{fmt(r.get('grid_ratio'), 1)} | {fmt(r.get('adaptive_points_per_s'))} | "
                       f"{fmt(r.get('adaptive_vs_grid'), 2)} |")
        out.append("")
    if "seeds" in results:
        out += ["## (c) Total training points/s vs vmapped seeds (discrete)", "",
                "Mode `map`: the same seeds one "
                "after another in one program (`lax.map`, as `hedger_jax.sharding.shard_seeds` "
                "runs a CPU device's seeds; across devices see `benchmarks/seeds_sharded.py`); "
                "`vs 1 seed` is against the first row of the index.", "",
                "| index | mode | capacity | stored | seeds | total points/s | wall | per seed "
                "| vs 1 seed | vs baseline |", "|---|---|---|---|---|---|---|---|---|---|"]
        for r in results["seeds"]:
            out.append(f"| {r['index']} | {r.get('mode', 'vmap')} | {r['capacity']:,} | "
                       f"{r['prefill']:,} | {r['seeds']} | "
                       f"{fmt(r['total_points_per_s'])} | {fmt(r['total_points_per_wall_s'])} | "
                       f"{fmt(r['per_seed_points_per_s'])} | "
                       f"{fmt(r['speedup_vs_1_seed'], 2)} | {fmt(r['ratio_vs_baseline'], 1)} |")
        out.append("")
    if "compile" in results:
        out += ["## (d) jit compile time of a full `make_train(...).train` (capacity 20,000)", "",
                "| actions | index | trace+lower s | compile s (wall) | compile CPU s | total s |",
                "|---|---|---|---|---|---|"]
        for r in results["compile"]:
            out.append(f"| {r['actions']} | {r['index']} | {fmt(r['trace_lower_s'], 1)} | "
                       f"{fmt(r['compile_s'], 1)} | {fmt(r['compile_cpu_s'], 1)} | "
                       f"{fmt(r['total_s'], 1)} |")
        out.append("")
    out += ["## (e) Peak resident memory (maxrss) after each section", "",
            "| section | maxrss MB |", "|---|---|"]
    for k, v in results["maxrss_mb"].items():
        out.append(f"| {k} | {v:,.0f} |")
    out.append("")
    return "\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (about a minute)")
    ap.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results"))
    ap.add_argument("--sections", default="predict,select,train,seeds,compile",
                    help="comma-separated sections to run: predict, select, train, seeds, "
                         "compile (default: all)")
    ap.add_argument("--default", action="store_true",
                    help="measure without hedger_jax.cpu.configure() (what a program gets "
                         "that only uses hedger_jax.jit); default: configure first")
    args = ap.parse_args(argv)
    configured = False if args.default else hj_cpu.configure()
    sections = args.sections.split(",")
    rng = np.random.default_rng(0)
    results = {"date": datetime.datetime.now().isoformat(timespec="seconds"),
               "quick": args.quick,
               "machine": {"cpu_count": os.cpu_count(), "cpu": cpu_model(),
                           "platform": platform.platform(),
                           "jax": jax.__version__, "backend": jax.default_backend(),
                           "load_start": os.getloadavg(),
                           "xla_flags": os.environ.get("XLA_FLAGS", ""),
                           "configured": configured},
               "maxrss_mb": {"start": maxrss_mb()}}
    if args.quick:
        caps, batch = [1_000, 10_000, 100_000], 1024
        train_settings = [(False, 20_000, 10_000), (True, 20_000, 10_000)]
        seed_counts = [1, 4, 16]
    else:
        caps, batch = [1_000, 10_000, 100_000, 300_000, 1_000_000], 4096
        train_settings = [(False, 20_000, 10_000), (True, 20_000, 10_000),
                          (False, 300_000, 200_000), (True, 300_000, 200_000),
                          (False, 1_000_000, 900_000)]
        seed_counts = [1, 4, 16, 64]
    if "predict" in sections:
        bench_predict(caps, batch, rng, results,
                      scaling=(10_000, 100_000) if args.quick else (10_000, 300_000))
        results["maxrss_mb"]["predict"] = maxrss_mb()
    if "select" in sections:
        bench_select(caps, batch, rng, results)
        results["maxrss_mb"]["select"] = maxrss_mb()
    if "train" in sections:
        bench_train(train_settings, rng, results, args.quick)
        results["maxrss_mb"]["train"] = maxrss_mb()
    if "seeds" in sections:
        base = next((r["baseline_points_per_s"] for r in results.get("train", [])
                     if r["actions"] == "discrete" and r["capacity"] == 20_000), None)
        for kind in ("brute", "grid"):
            bench_seeds(seed_counts, 20_000, 10_000, rng, results, args.quick, kind, base)
        results["maxrss_mb"]["seeds"] = maxrss_mb()
    if "compile" in sections:
        bench_compile(results)
        results["maxrss_mb"]["compile"] = maxrss_mb()
    results["machine"]["load_end"] = os.getloadavg()
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "benchmark.json"), "w") as fh:
        json.dump(results, fh, indent=1)
    md = markdown(results)
    with open(os.path.join(args.out, "benchmark.md"), "w") as fh:
        fh.write(md)
    print(md)
    return results


if __name__ == "__main__":
    main()
