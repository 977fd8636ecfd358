"""Run a figure's variants over batches of seeds, block by block, resumably.

For each variant the seeds are split into batches (``seed_batch``); each batch is one
``jax.jit(jax.vmap(run_block))`` (or, ``seed_mode="map"``, ``jax.jit(lax.map(run_block))``)
computation per evaluation block. After every block the
batch's state (memories included) and results so far are checkpointed atomically, so an
interrupted sweep resumes where it stopped without redoing finished work; a finished batch
is written once, atomically, as a result file and never recomputed (a result cache keyed on
the variant, its seeds and the library version, shared between figures).

Seed ``i`` always uses ``jax.random.fold_in(PRNGKey(base_seed), i)``, so results do not
depend on how seeds are batched.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
from typing import Any, Callable, Dict, List, Optional

import jax
import jax.numpy as jnp
import numpy as np

import hedger_jax
from hedger_jax.agent import BlockResult, make_train, transitions_from_demonstrations
from hedger_jax.config import HedgerConfig
from hedger_jax.cpu import jit as _jit
from hedger_jax.files import atomic_write
from hedger_jax.memory import memory_check

from experiments.figures import Variant


def atomic_write_bytes(path: str, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically, with the permissions ``open`` would give."""
    atomic_write(path, lambda f: f.write(data))


def atomic_write_json(path: str, obj: Any) -> None:
    atomic_write_bytes(path, json.dumps(obj, indent=1, sort_keys=True).encode())


def variant_key(variant: Variant, seeds: List[int], base_seed: int) -> str:
    """A stable hash of everything that determines a variant's results for these seeds.

    The label is left out (it names a line in a plot, it does not change the run), so the
    same run shared by two figures under different labels is computed once.
    """
    blob = json.dumps({
        "variant": repr(dataclasses.replace(variant, label="")), "seeds": seeds,
        "base_seed": base_seed,
        "version": hedger_jax.__version__,
    }, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def build_variant(variant: Variant):
    """(env, HedgerConfig, Train, phase1 description) for a variant."""
    import envs

    env = envs.make(variant.env)
    config = config_of(variant)
    env_params = env_params_of(env, variant)
    phase1 = None
    info: Dict[str, Any] = {}
    if variant.phase1 == "simulated_person":
        from envs.demonstrators import simulated_person_demonstrations

        demos = simulated_person_demonstrations(seed=0)
        lengths = np.asarray(demos.valid).sum(axis=1)
        info = {"demonstrations": int(lengths.size), "demo_lengths": lengths.tolist(),
                "demo_mean_steps": float(lengths.mean())}
        phase1 = transitions_from_demonstrations(demos)
    elif variant.phase1 == "hand_coded":
        from envs.corridor_controllers import hand_coded_policy

        phase1 = (hand_coded_policy(), variant.phase1_episodes)
        info = {"phase1_episodes": variant.phase1_episodes, "phase1_policy": "hand_coded"}
    elif variant.phase1 is not None:
        raise ValueError(f"unknown phase1 source {variant.phase1!r}")
    train = make_train(env, config, variant.run, phase1=phase1, env_params=env_params)
    return env, config, train, info


SEED_MODES = ("auto", "vmap", "map")


def resolve_seed_mode(seed_mode: str) -> str:
    """"vmap" or "map" for a ``seed_mode`` ("auto": map on the CPU backend, else vmap)."""
    if seed_mode not in SEED_MODES:
        raise ValueError(f"seed_mode: expected one of {SEED_MODES}, got {seed_mode!r}")
    if seed_mode == "auto":
        return "map" if jax.default_backend() == "cpu" else "vmap"
    return seed_mode


@functools.lru_cache(maxsize=32)
def compiled_variant(variant: Variant, seed_mode: str = "vmap", n_devices: int = 1):
    """(init, run_block donating its state, phase-1 info) over a batch of seeds, cached per
    variant and mode so that repeated and resumed runs in one process compile once per batch
    size. seed_mode "vmap": ``jit(vmap(...))``; "map": ``jit(lax.map(...))``, the batch's
    seeds one after another in one program (on a CPU each then runs at the one-seed rate;
    vmapped seeds share the batched kernels and wait for the longest episode). With
    ``n_devices`` > 1 the batch's seeds are split over the first ``n_devices`` devices
    (``hedger_jax.sharding.per_device``): batches must then be a multiple of it long."""
    _, config, train, info = build_variant(variant)
    if seed_mode not in ("map", "vmap"):
        raise ValueError(f"seed_mode: expected 'vmap' or 'map', got {seed_mode!r}")
    if n_devices > 1:
        from hedger_jax.sharding import per_device, seed_mesh

        mesh = seed_mesh(jax.devices()[:n_devices])
        sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("seeds"))
        shard = dict(in_shardings=sharding, out_shardings=sharding)
        batched_init = per_device(train.init, mesh, seed_mode)
        batched_block = per_device(train.run_block, mesh, seed_mode)
    else:
        shard = {}
        if seed_mode == "map":
            batched_init = functools.partial(jax.lax.map, train.init)
            batched_block = functools.partial(jax.lax.map, train.run_block)
        else:
            batched_init, batched_block = jax.vmap(train.init), jax.vmap(train.run_block)
    init = _jit(batched_init, **shard)
    run_block = _jit(batched_block, donate_argnums=0, **shard)
    return init, run_block, info


def usable_devices(devices: Optional[int]) -> int:
    """How many devices a run splits its seed batches over: ``devices`` (None: all of
    ``jax.devices()``), at most as many as there are."""
    have = len(jax.devices())
    if devices is None:
        return have
    if int(devices) < 1:
        raise ValueError(f"devices: must be >= 1, got {devices}")
    return min(int(devices), have)


def _to_numpy(tree):
    return jax.tree_util.tree_map(lambda x: np.asarray(x), tree)


def _save_checkpoint(path: str, state, results: List[BlockResult], block: int, key: str):
    leaves = jax.tree_util.tree_leaves(_to_numpy(state))
    res_leaves = jax.tree_util.tree_leaves(
        _to_numpy(jax.tree_util.tree_map(lambda *xs: np.stack(xs, 1), *results)))
    import io

    buf = io.BytesIO()
    arrays = {f"s{i}": a for i, a in enumerate(leaves)}
    arrays.update({f"r{i}": a for i, a in enumerate(res_leaves)})
    arrays["meta"] = np.frombuffer(json.dumps({"block": block, "key": key}).encode(), np.uint8)
    np.savez(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def _load_checkpoint(path: str, state_like, result_like, key: str):
    """(state, results list, block) or None if absent / for another variant / unreadable."""
    if not os.path.exists(path):
        return None
    try:
        with np.load(path) as z:
            meta = json.loads(bytes(z["meta"]).decode())
            if meta.get("key") != key:
                return None
            s_leaves, s_def = jax.tree_util.tree_flatten(state_like)
            r_leaves, r_def = jax.tree_util.tree_flatten(result_like)
            state = jax.tree_util.tree_unflatten(
                s_def, [jnp.asarray(z[f"s{i}"]) for i in range(len(s_leaves))])
            stacked = [z[f"r{i}"] for i in range(len(r_leaves))]
            # Shapes as this run's (e.g. not padded for another number of devices).
            for got, like in zip(jax.tree_util.tree_leaves(state), s_leaves):
                if got.shape != like.shape or got.dtype != like.dtype:
                    raise ValueError(f"state leaf {got.shape} {got.dtype}, this run's "
                                     f"{like.shape} {like.dtype}")
            for got, like in zip(stacked, r_leaves):
                if got.shape[:1] + got.shape[2:] != like.shape[:1] + like.shape[1:]:
                    raise ValueError(f"result leaf {got.shape}, this run's {like.shape}")
    except Exception as err:  # a corrupt checkpoint is ignored (the run restarts), not trusted
        print(f"warning: ignoring unreadable checkpoint {path}: {err}")
        return None
    n_done = stacked[0].shape[1]
    results = [jax.tree_util.tree_unflatten(r_def, [a[:, j] for a in stacked])
               for j in range(n_done)]
    return state, results, int(meta["block"])


def run_variant(variant: Variant, seeds: List[int], out_dir: str, *, base_seed: int = 0,
                seed_batch: int = 8, progress: bool = True,
                on_block: Optional[Callable[[int], None]] = None,
                seed_mode: str = "vmap", devices: Optional[int] = 1) -> Dict[str, Any]:
    """Run (or resume, or load) one variant over ``seeds``. Returns its result record.

    ``seed_mode``: how a batch's seeds run ("vmap" | "map" | "auto", ``compiled_variant``).
    Results agree statistically between modes and batch sizes, not bit for bit, and the
    result cache does not tell them apart (as for ``seed_batch``). ``devices``: split each
    batch over this many devices (None: all; a batch is padded to a multiple of them by
    repeating its last seed, whose copies are dropped from the results). With "map" a seed's
    numbers do not depend on the device or the batch.

    The record holds, per evaluation (block 0 = after phase 1): ``points`` and ``episodes``
    (seeds, blocks+1) and ``mean_steps``/``success_rate`` (seeds, blocks+1).
    """
    key = variant_key(variant, seeds, base_seed)
    cache_dir = os.path.join(out_dir, "cache")
    result_path = os.path.join(cache_dir, f"{key}.json")
    if os.path.exists(result_path):
        with open(result_path) as f:
            record = json.load(f)
        if record.get("complete"):
            if progress:
                print(f"  {variant.label}: cached result {result_path}")
            # The cache is shared between figures that name the same run differently.
            return dict(record, label=variant.label)

    n_dev = usable_devices(devices)
    init, run_block, info = compiled_variant(variant, resolve_seed_mode(seed_mode), n_dev)
    n_blocks = variant.run.n_blocks
    batches = [seeds[i:i + seed_batch] for i in range(0, len(seeds), seed_batch)]
    per_batch: List[Dict[str, np.ndarray]] = []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(batches) * (n_blocks + 1), desc=f"  {variant.label}",
                   unit="eval", leave=True)
    for b, batch in enumerate(batches):
        batch_key = variant_key(variant, batch, base_seed)
        batch_path = os.path.join(cache_dir, f"batch-{batch_key}.json")
        if os.path.exists(batch_path):
            with open(batch_path) as f:
                per_batch.append({k: np.asarray(v) for k, v in json.load(f).items()})
            if bar is not None:
                bar.update(n_blocks + 1)
            continue
        ckpt_path = os.path.join(cache_dir, f"ckpt-{batch_key}.npz")
        padded = batch + [batch[-1]] * ((-len(batch)) % n_dev)
        keys = jnp.stack([jax.random.fold_in(jax.random.PRNGKey(base_seed), s) for s in padded])
        state_like, first_like = jax.eval_shape(init, keys)
        resumed = _load_checkpoint(ckpt_path, state_like, first_like, batch_key)
        if resumed is None:
            state, first = init(keys)
            memory_check(state.memory)
            results = [first]
            done = 0
            _save_checkpoint(ckpt_path, state, results, done, batch_key)
        else:
            state, results, done = resumed
            if n_dev > 1:   # the checkpoint's arrays, split over the devices as run_block wants
                state = jax.device_put(state, jax.sharding.NamedSharding(
                    jax.sharding.Mesh(np.asarray(jax.devices()[:n_dev], dtype=object),
                                      ("seeds",)), jax.sharding.PartitionSpec("seeds")))
        if bar is not None:
            bar.update(done + 1)
        for blk in range(done, n_blocks):
            state, res = run_block(state)
            memory_check(state.memory)
            results.append(res)
            _save_checkpoint(ckpt_path, state, results, blk + 1, batch_key)
            if bar is not None:
                steps = np.asarray(res.evaluation.mean_steps)[:len(batch)]
                bar.set_postfix(steps=f"{float(np.mean(steps)):.1f}")
                bar.update(1)
            if on_block is not None:
                on_block(blk + 1)
        stacked = jax.tree_util.tree_map(
            lambda *xs: np.stack([np.asarray(x)[:len(batch)] for x in xs], 1), *results)
        arrays = {
            "points": stacked.points, "episodes": stacked.episodes,
            "mean_steps": stacked.evaluation.mean_steps,
            "success_rate": stacked.evaluation.success_rate,
            "train_steps_mean": stacked.train_steps_mean,
            "memory_size": stacked.memory_size,
        }
        atomic_write_json(batch_path, {k: np.asarray(v).tolist() for k, v in arrays.items()})
        per_batch.append(arrays)
        if os.path.exists(ckpt_path):
            os.unlink(ckpt_path)
    if bar is not None:
        bar.close()
    merged = {k: np.concatenate([np.asarray(p[k]) for p in per_batch], 0).tolist()
              for k in per_batch[0]}
    record = {
        "label": variant.label, "env": variant.env, "x_axis": variant.x_axis,
        "seeds": seeds, "base_seed": base_seed, "phase1": variant.phase1, "phase1_info": info,
        "hedger_config": dataclasses.asdict(config_of(variant)),
        "env_params": dict(variant.env_params),
        "run_config": dataclasses.asdict(variant.run),
        "versions": versions(), "complete": True, **merged,
    }
    atomic_write_json(result_path, record)
    return record


def config_of(variant: Variant) -> HedgerConfig:
    """The HedgerConfig a variant runs with."""
    import envs

    config = HedgerConfig.for_env(envs.make(variant.env), **variant.hedger_kwargs())
    if variant.state_scale_factors is not None:
        factors = tuple(variant.state_scale_factors) + (1.0,) * config.action_dim
        config = config.replace(input_scale=tuple(
            s * f for s, f in zip(config.input_scale, factors)))
    return config


def env_params_of(env: Any, variant: Variant) -> Any:
    """The env's default params with the variant's overrides (as float32 leaves)."""
    params = env.default_params()
    if variant.env_params:
        params = dataclasses.replace(params, **{k: jnp.float32(v) for k, v in variant.env_params})
    return params


def versions() -> Dict[str, str]:
    import platform

    import gymnasium

    return {"hedger_jax": hedger_jax.__version__, "jax": jax.__version__,
            "numpy": np.__version__, "gymnasium": gymnasium.__version__,
            "python": platform.python_version(), "backend": jax.default_backend()}
