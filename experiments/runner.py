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
import time
from typing import Any, Callable, Dict, List, Optional

import jax
import jax.numpy as jnp
import numpy as np

import hedger_jax
from hedger_jax.agent import BlockResult, make_train, transitions_from_demonstrations
from hedger_jax.config import HedgerConfig, selection_radius
from hedger_jax.cpu import jit as _jit
from hedger_jax.files import atomic_write
from hedger_jax.memory import memory_check
from hedger_jax.params import HedgerParams
from hedger_jax.distributed import compile_shared
from hedger_jax.sharding import gather, global_put, shared_settings, with_shared_settings

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


def build_variant(variant: Variant, config: Optional[HedgerConfig] = None):
    """(env, HedgerConfig, Train, phase1 description) for a variant (``config``: instead of
    the variant's own, e.g. a group's, ``group_config``)."""
    import envs

    env = envs.make(variant.env)
    config = config_of(variant) if config is None else config
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


def static_part(variant: Variant) -> Variant:
    """The variant without its label and its traced settings: what fixes the program. Variants
    with equal static parts run as one program (a sweep over their ``params``)."""
    return dataclasses.replace(variant, label="", params=())


def group_config(variants: List[Variant]) -> HedgerConfig:
    """The static config of a group of variants sharing a static part: theirs, with
    ``max_bandwidth`` raised so that the grid index covers the widest selection radius any
    of them uses (a wider bandwidth, a smaller min_weight, a data-chosen kernel's range)."""
    config = config_of(variants[0])
    radius = lambda p: selection_radius(  # noqa: E731
        p.get("bandwidth", config.bandwidth), p.get("min_weight", config.min_weight),
        p.get("kernel_range", config.kernel_range), p.get("bandwidth_k", config.bandwidth_k))
    widest = max(radius(dict(v.params)) for v in variants)
    needed = config.bandwidth * widest / config.k_thresh
    return config.replace(max_bandwidth=max(needed, config.max_bandwidth))


def params_of(variant: Variant, config: HedgerConfig) -> HedgerParams:
    """The traced settings of a variant: the config's values with the variant's ``params``
    overrides (``action_scale`` scales the config's action input scale)."""
    overrides = dict(variant.params)
    if "action_scale" in overrides:
        factor = float(overrides.pop("action_scale"))
        scale = np.asarray(config.input_scale, np.float64)
        scale[config.state_dim:] *= factor / dict(variant.hedger).get("action_scale", 1.0)
        overrides["input_scale"] = scale
    return HedgerParams.create(config, variant.run, **overrides)


@functools.lru_cache(maxsize=32)
def compiled_group(static: Variant, config: HedgerConfig, seed_mode: str = "vmap",
                   n_devices: int = 1, shared: Optional[tuple] = None):
    """(init, run_block donating its state, phase-1 info) over a batch of members (a seed
    and its settings each: ``init(keys, params)``, ``run_block(state, params)``), cached per
    static part, config, mode and shared settings so that repeated and resumed runs in one
    process compile once per batch size. shared: None (params: ``HedgerParams`` with a
    leading member axis), or (treedef, constants) of ``hedger_jax.sharding.shared_settings``:
    the settings every member of the group shares are then constants of the programs, and
    params is the list of the other leaves (each with the member axis). seed_mode "vmap": ``jit(vmap(...))``; "map": ``jit(lax.map(...))``,
    the batch's members one after another in one program (on a CPU each then runs at the
    one-seed rate; vmapped members share the batched kernels and wait for the longest
    episode). With ``n_devices`` > 1 the members are split over the first ``n_devices``
    devices (``hedger_jax.sharding.per_device``): batches must then be a multiple of it."""
    _, _, train, info = build_variant(static, config)
    if shared is not None:       # compiles about twice as fast as with every setting traced
        train = train._replace(init=with_shared_settings(train.init, *shared),
                               run_block=with_shared_settings(train.run_block, *shared))
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
            def batched_init(keys, params):
                return jax.lax.map(lambda a: train.init(*a), (keys, params))

            def batched_block(state, params):
                return jax.lax.map(lambda a: train.run_block(*a), (state, params))
        else:
            batched_init, batched_block = jax.vmap(train.init), jax.vmap(train.run_block)
    init = _jit(batched_init, **shard)
    run_block = _jit(batched_block, donate_argnums=0, **shard)
    return init, run_block, info


def usable_devices(devices: Optional[int]) -> int:
    """How many devices a run splits its seed batches over: ``devices`` (None: all of
    ``jax.devices()``), at most as many as there are; across processes always all of them
    (every process must take part in each program)."""
    have = len(jax.devices())
    if devices is None or jax.process_count() > 1:    # several processes: all of their devices
        return have
    if int(devices) < 1:
        raise ValueError(f"devices: must be >= 1, got {devices}")
    return min(int(devices), have)


def _member_slices(leaf) -> List[tuple]:
    """(first member, NumPy block of members) for each shard of ``leaf`` this process holds."""
    out, seen = [], set()
    for shard in leaf.addressable_shards:
        first = (shard.index[0].start or 0) if shard.index else 0
        if first not in seen:                 # replicated shards hold the same members
            seen.add(first)
            out.append((first, np.asarray(shard.data)))
    return out


def owned_members(tree) -> Dict[int, Any]:
    """{member index: that member's pytree (NumPy)} for the members (leading axis) whose data
    this process holds: all of them in one process, its devices' share across processes."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    per_member: Dict[int, List[np.ndarray]] = {}
    for leaf in leaves:
        for first, block in _member_slices(leaf):
            for k in range(block.shape[0]):
                per_member.setdefault(first + k, []).append(block[k])
    return {j: jax.tree_util.tree_unflatten(treedef, xs) for j, xs in per_member.items()
            if len(xs) == len(leaves)}


def _ckpt_path(cache_dir: str, batch_key: str, member: int, block: int) -> str:
    return os.path.join(cache_dir, f"ckpt-{batch_key}-m{member}-b{block}.npz")


def _ckpt_blocks(cache_dir: str, batch_key: str) -> Dict[int, List[int]]:
    """{member: blocks with a checkpoint file} of a batch."""
    prefix, found = f"ckpt-{batch_key}-m", {}
    for name in os.listdir(cache_dir) if os.path.isdir(cache_dir) else ():
        if name.startswith(prefix) and name.endswith(".npz"):
            member, _, block = name[len(prefix):-4].partition("-b")
            if member.isdigit() and block.isdigit():
                found.setdefault(int(member), []).append(int(block))
    return found


def _save_member(path: str, state, results, block: int, key: str) -> None:
    """One member's state and its results of blocks 0..block (leaves stacked on axis 0)."""
    import io

    arrays = {f"s{i}": np.asarray(a) for i, a in enumerate(jax.tree_util.tree_leaves(state))}
    arrays.update({f"r{i}": np.asarray(a)
                   for i, a in enumerate(jax.tree_util.tree_leaves(results))})
    arrays["meta"] = np.frombuffer(json.dumps({"block": block, "key": key}).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def _load_member(path: str, state_like, results_like, block: int, key: str):
    """(state, results) of one member (NumPy, shapes as ``*_like``), or None if the file is
    missing, for another batch or block, or unreadable."""
    try:
        with np.load(path) as z:
            meta = json.loads(bytes(z["meta"]).decode())
            if meta.get("key") != key or meta.get("block") != block:
                return None
            trees = []
            for prefix, like in (("s", state_like), ("r", results_like)):
                leaves, treedef = jax.tree_util.tree_flatten(like)
                got = [z[f"{prefix}{i}"] for i in range(len(leaves))]
                for g, l in zip(got, leaves):
                    if g.shape != l.shape or g.dtype != l.dtype:
                        raise ValueError(f"leaf {g.shape} {g.dtype}, this run's {l.shape} "
                                         f"{l.dtype}")
                trees.append(jax.tree_util.tree_unflatten(treedef, got))
    except Exception as err:  # a corrupt checkpoint is ignored (the run restarts), not trusted
        print(f"warning: ignoring unreadable checkpoint {path}: {err}")
        return None
    return tuple(trees)


def _member_like(tree):
    """Shapes of one member of a batched pytree of shapes."""
    return jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct(x.shape[1:], x.dtype), tree)


def _blocks_like(tree, n_blocks: int):
    """Shapes of ``n_blocks`` stacked copies of one member's pytree of shapes."""
    return jax.tree_util.tree_map(
        lambda x: jax.ShapeDtypeStruct((n_blocks,) + x.shape, x.dtype), tree)


def _cached(path: str) -> Optional[Dict[str, Any]]:
    if os.path.exists(path):
        with open(path) as f:
            record = json.load(f)
        if record.get("complete"):
            return record
    return None


def run_variant(variant: Variant, seeds: List[int], out_dir: str, **kwargs) -> Dict[str, Any]:
    """Run (or resume, or load) one variant over ``seeds``: ``run_sweep`` of one."""
    return run_sweep([variant], seeds, out_dir, **kwargs)[0]


def run_sweep(variants: List[Variant], seeds: List[int], out_dir: str, *, base_seed: int = 0,
              seed_batch: Optional[int] = 8, progress: bool = True,
              on_block: Optional[Callable[[int], None]] = None,
              seed_mode: str = "vmap", devices: Optional[int] = 1,
              label: Optional[str] = None) -> List[Dict[str, Any]]:
    """Run (or resume, or load) variants that share a static part (``static_part``) over
    ``seeds``, as ONE compiled program: each batch holds (variant, seed) members, each with
    its own ``HedgerParams``. Returns one result record per variant, in order.

    ``seed_batch``: members per program call (None: all of them at once). ``seed_mode``:
    how a batch's members run ("vmap" | "map" | "auto", ``compiled_group``). Results agree
    statistically between modes and batch sizes, not bit for bit, and the result cache does
    not tell them apart. ``devices``: split each batch over this many devices (None: all; a
    batch is padded to a multiple of them by repeating its last member, whose copies are
    dropped). With "map" a member's numbers do not depend on the device or the batch.

    A record holds, per evaluation (block 0 = after phase 1): ``points`` and ``episodes``
    (seeds, blocks+1) and ``mean_steps``/``success_rate`` (seeds, blocks+1). Each variant's
    finished record is cached under its own key (``variant_key``), shared between figures;
    batches checkpoint after every block and resume.
    """
    statics = {static_part(v) for v in variants}
    if len(statics) != 1:
        raise ValueError("run_sweep: the variants differ in more than their params; run "
                         "them separately")
    cache_dir = os.path.join(out_dir, "cache")
    paths = [os.path.join(cache_dir, f"{variant_key(v, seeds, base_seed)}.json")
             for v in variants]
    # Process 0's view of what is on disk, so that every process takes the same branches.
    found = _as_process_zero([_cached(p) is not None for p in paths])
    records: List[Optional[Dict[str, Any]]] = [_cached(p) if f else None
                                               for p, f in zip(paths, found)]
    todo = [i for i, r in enumerate(records) if r is None]
    for i, rec in enumerate(records):
        if rec is not None and progress and jax.process_index() == 0:
            print(f"  {variants[i].label}: cached result {paths[i]}")
    if todo:
        t0 = time.time()
        arrays = _run_members([variants[i] for i in todo], seeds, cache_dir, base_seed,
                              seed_batch, progress, on_block, seed_mode, devices, label)
        share = (time.time() - t0) / len(todo)    # the sweep's wall time, shared evenly
        config = group_config(variants)
        for j, i in enumerate(todo):
            v = variants[i]
            record = {
                "label": v.label, "env": v.env, "x_axis": v.x_axis,
                "seeds": seeds, "base_seed": base_seed, "phase1": v.phase1,
                "phase1_info": arrays["info"],
                "hedger_config": dataclasses.asdict(config),
                "params": {k: _jsonable(x) for k, x in params_of(v, config)._asdict().items()},
                "env_params": dict(v.env_params),
                "run_config": dataclasses.asdict(v.run),
                "versions": versions(), "complete": True, "compute_seconds": share,
                **{k: a[j].tolist() for k, a in arrays["per_variant"].items()},
            }
            if jax.process_index() == 0:
                atomic_write_json(paths[i], record)
            records[i] = record
    return [dict(r, label=v.label) for r, v in zip(records, variants)]


def _jsonable(x):
    a = np.asarray(x)
    return a.item() if a.ndim == 0 else a.tolist()


def _run_members(variants: List[Variant], seeds: List[int], cache_dir: str, base_seed: int,
                 seed_batch: Optional[int], progress: bool,
                 on_block: Optional[Callable[[int], None]], seed_mode: str,
                 devices: Optional[int], label: Optional[str]) -> Dict[str, Any]:
    """Run every (variant, seed) member in batches of one program; -> {"info": phase-1 info,
    "per_variant": {field: array (variants, seeds, blocks + 1)}}."""
    config = group_config(variants)
    n_dev = usable_devices(devices)
    # The settings every variant shares become constants of the program.
    treedef, constants, varying = shared_settings(jax.tree_util.tree_map(
        lambda *xs: np.stack([np.asarray(x) for x in xs]),
        *[params_of(v, config) for v in variants]))
    init, run_block, info = compiled_group(static_part(variants[0]), config,
                                           resolve_seed_mode(seed_mode), n_dev,
                                           (treedef, constants))
    all_params = [[jax.tree_util.tree_leaves(params_of(v, config))[i] for i in varying]
                  for v in variants]
    members = [(i, s) for i in range(len(variants)) for s in seeds]
    size = len(members) if seed_batch is None else int(seed_batch)
    batches = [members[i:i + size] for i in range(0, len(members), size)]
    n_blocks = variants[0].run.n_blocks
    bar = None
    if progress and jax.process_index() == 0:
        from tqdm.auto import tqdm

        desc = label or (variants[0].label if len(variants) == 1 else
                         f"{len(variants)} settings")
        bar = tqdm(total=len(batches) * (n_blocks + 1), desc=f"  {desc}", unit="eval",
                   leave=True)
    fields = ("points", "episodes", "mean_steps", "success_rate", "train_steps_mean",
              "memory_size")
    out = {f: {} for f in fields}
    for batch in batches:
        batch_key = hashlib.sha256(json.dumps(
            [variant_key(variants[i], [s], base_seed) for i, s in batch]).encode()
        ).hexdigest()[:16]
        batch_path = os.path.join(cache_dir, f"batch-{batch_key}.json")
        if _as_process_zero([os.path.exists(batch_path)])[0]:
            with open(batch_path) as f:
                arrays = {k: np.asarray(v) for k, v in json.load(f).items()}
            if bar is not None:
                bar.update(n_blocks + 1)
        else:
            arrays = _run_batch(batch, all_params, base_seed, n_dev, init, run_block,
                                n_blocks, cache_dir, batch_key, bar, on_block)
            if jax.process_index() == 0:      # one writer; every process has the results
                atomic_write_json(batch_path,
                                  {k: np.asarray(v).tolist() for k, v in arrays.items()})
            _barrier(f"done-{batch_key}")
            _remove_checkpoints(cache_dir, batch_key, set(range(len(batch))))
        for j, member in enumerate(batch):
            for f in fields:
                out[f][member] = np.asarray(arrays[f])[j]
    if bar is not None:
        bar.close()
    per_variant = {f: np.stack([np.stack([out[f][(i, s)] for s in seeds])
                                for i in range(len(variants))]) for f in fields}
    return {"info": info, "per_variant": per_variant}


def _member_sharding(n_dev: int):
    """How a batch's members are split: over the first ``n_dev`` devices (None: one device)."""
    if n_dev == 1:
        return None
    mesh = jax.sharding.Mesh(np.asarray(jax.devices()[:n_dev], dtype=object), ("seeds",))
    return jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("seeds"))


def _place(tree, sharding):
    """Host arrays (equal on every process) on the devices, split by ``sharding``."""
    if sharding is None:
        return jax.tree_util.tree_map(jnp.asarray, tree)
    return global_put(tree, sharding)


def _check_memories(state) -> None:
    """``memory_check`` on every member's memory (flags gathered from every process)."""
    memory_check(state.memory._replace(flags=gather(state.memory.flags)))


def _barrier(name: str) -> None:
    """Wait for every process (a no-op in one process)."""
    from hedger_jax.distributed import barrier

    barrier(name)


def _as_process_zero(flags: List[bool]) -> List[bool]:
    """Process 0's ``flags`` on every process (a no-op in one process)."""
    if jax.process_count() == 1:
        return list(flags)
    from jax.experimental import multihost_utils

    _barrier("broadcast")
    return [bool(f) for f in multihost_utils.broadcast_one_to_all(np.asarray(flags, bool))]


def _every_process(value: int) -> np.ndarray:
    """Every process's ``value`` (int32 (processes,)), on every process."""
    if jax.process_count() == 1:
        return np.array([value], np.int32)
    return np.asarray(gather(np.array([value], np.int32)))


def _remove_checkpoints(cache_dir: str, batch_key: str, members=None, blocks=None) -> None:
    """Delete a batch's checkpoint files (only these members / blocks when given)."""
    for j, bs in _ckpt_blocks(cache_dir, batch_key).items():
        for b in bs:
            if (members is None or j in members) and (blocks is None or b in blocks):
                try:
                    os.unlink(_ckpt_path(cache_dir, batch_key, j, b))
                except FileNotFoundError:     # another process's copy of a padded member
                    pass


def _save_block(cache_dir: str, batch_key: str, state, results: List[Any], block: int,
                n: int) -> None:
    """Checkpoint this process's members after ``block``, then (once every process has) drop
    their previous block's files: some complete block is on disk for every member at all
    times, whatever the process count of the run that resumes it."""
    stacked = jax.tree_util.tree_map(lambda *xs: np.stack(xs), *results)
    members = owned_members(state)
    owned = [j for j in members if j < n]
    for j in owned:
        _save_member(_ckpt_path(cache_dir, batch_key, j, block), members[j],
                     jax.tree_util.tree_map(lambda x: x[:, j], stacked), block, batch_key)
    _barrier(f"ckpt-{batch_key}-{block}")
    if block > 0:
        _remove_checkpoints(cache_dir, batch_key, set(owned), set(range(block)))


def _resume(cache_dir: str, batch_key: str, n: int, padded_n: int, state_like, first_like,
            sharding):
    """(state placed as ``sharding``, host results per block, block) from the batch's member
    checkpoints, or None (then no checkpoint is left). Every process agrees on the block."""
    found = _ckpt_blocks(cache_dir, batch_key)
    done = min((max(found[j]) if found.get(j) else -1) for j in range(n))
    loaded = []
    if done >= 0:
        state1, res1 = _member_like(state_like), _blocks_like(_member_like(first_like), done + 1)
        for j in range(n):
            member = _load_member(_ckpt_path(cache_dir, batch_key, j, done), state1, res1,
                                  done, batch_key)
            if member is None:
                done = -1
                break
            loaded.append(member)
    found_by = _every_process(done)      # every process must take the same branch
    if found_by.min() < 0 or found_by.min() != found_by.max():
        _barrier(f"fresh-{batch_key}")
        if jax.process_index() == 0:
            _remove_checkpoints(cache_dir, batch_key)
        _barrier(f"cleared-{batch_key}")
        return None
    rows = [loaded[min(j, n - 1)] for j in range(padded_n)]   # padding repeats the last member
    leaves, treedef = jax.tree_util.tree_flatten(state_like)
    member_leaves = [jax.tree_util.tree_leaves(r[0]) for r in rows]
    if sharding is None:
        placed = [jnp.asarray(np.stack([m[i] for m in member_leaves])) for i in range(len(leaves))]
    else:
        placed = [jax.make_array_from_callback(
            like.shape, sharding,
            lambda index, i=i: np.stack([member_leaves[j][i]
                                         for j in range(padded_n)[index[0]]]))
            for i, like in enumerate(leaves)]
    state = jax.tree_util.tree_unflatten(treedef, placed)
    results = [jax.tree_util.tree_map(lambda *xs, b=b: np.stack([x[b] for x in xs]),
                                      *[r[1] for r in rows]) for b in range(done + 1)]
    return state, results, done


def _run_batch(batch, all_params, base_seed, n_dev, init, run_block, n_blocks, cache_dir,
               batch_key, bar, on_block) -> Dict[str, np.ndarray]:
    """One batch of members through init and every block, checkpointed after each block.
    Across processes each process runs and checkpoints its devices' members; the results are
    gathered to every process."""
    n = len(batch)
    padded = batch + [batch[-1]] * ((-n) % n_dev)
    keys = np.stack([np.asarray(jax.random.fold_in(jax.random.PRNGKey(base_seed), s))
                     for _, s in padded])
    params = [np.stack([np.asarray(all_params[i][j]) for i, _ in padded])
              for j in range(len(all_params[0]))]
    sharding = _member_sharding(n_dev)
    keys, params = _place((keys, params), sharding)
    state_like, first_like = jax.eval_shape(init, keys, params)
    resumed = _resume(cache_dir, batch_key, n, len(padded), state_like, first_like, sharding)
    several = jax.process_count() > 1     # then compiled once, by process 0 (docs/scaling.md)
    if resumed is None:
        if several:
            init = compile_shared(init, keys, params)
        state, first = init(keys, params)
        _check_memories(state)
        results = [gather(first)]
        done = 0
        _save_block(cache_dir, batch_key, state, results, done, n)
    else:
        state, results, done = resumed
    if several:
        run_block = compile_shared(run_block, state, params)
    if bar is not None:
        bar.update(done + 1)
    for blk in range(done, n_blocks):
        state, res = run_block(state, params)
        _check_memories(state)
        results.append(gather(res))
        _save_block(cache_dir, batch_key, state, results, blk + 1, n)
        if bar is not None:
            steps = np.asarray(results[-1].evaluation.mean_steps)[:n]
            bar.set_postfix(steps=f"{float(np.mean(steps)):.1f}")
            bar.update(1)
        if on_block is not None:
            on_block(blk + 1)
    stacked = jax.tree_util.tree_map(
        lambda *xs: np.stack([np.asarray(x)[:n] for x in xs], 1), *results)
    return {"points": stacked.points, "episodes": stacked.episodes,
            "mean_steps": stacked.evaluation.mean_steps,
            "success_rate": stacked.evaluation.success_rate,
            "train_steps_mean": stacked.train_steps_mean,
            "memory_size": stacked.memory_size}


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
