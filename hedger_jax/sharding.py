"""Sweeps split over devices: ``sweep(train, keys, params)``.

Each device runs its share of the members (a seed and, optionally, its settings) inside one
jitted program (``jax.shard_map`` over a 1-D mesh named ``"seeds"``)::

    train = make_train(env, config, run).train
    results = sweep(train, keys, params)        # every device of every process

Within a device the members run either vmapped (``per_device="vmap"``: one batched program,
what a GPU wants) or one after another (``"map"``: ``lax.map``, the single-member program in
a loop). ``"auto"`` (default) picks ``"map"`` on CPU devices and ``"vmap"`` on accelerators.
Why: on a CPU a vmapped episode loop runs until its longest member ends and the batched index
and fit kernels cost about as much per member as one member's, so vmapped members add no
throughput, while ``map`` keeps every member at the single-member rate and the devices run
side by side.

The member count need not divide the device count: the inputs are padded by repeating the
last member and the padding is cut from the outputs. A member's result does not depend on
the device it ran on or on how many others shared it (``"map"``: the single-member program;
``"vmap"``: as ``jax.vmap(train_fn)``). On a CPU, split it into N devices with
``hedger_jax.cpu.configure(host_devices=N)`` before JAX starts; across machines, join the
processes first with ``hedger_jax.distributed.initialize()`` (docs/scaling.md).
"""
from __future__ import annotations

import functools
from typing import Any, Callable, Optional, Sequence, Tuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from hedger_jax.cpu import jit as _jit

#: Name of the mesh axis the seeds are split over.
AXIS = "seeds"
#: ``per_device`` choices (module doc).
PER_DEVICE_MODES = ("auto", "map", "vmap")


def seed_mesh(devices: Optional[Sequence[Any]] = None) -> Mesh:
    """A 1-D mesh (axis ``"seeds"``) over ``devices`` (default: all of ``jax.devices()``)."""
    devs = list(jax.devices() if devices is None else devices)
    if not devs:
        raise ValueError("devices: need at least one device")
    return Mesh(np.asarray(devs, dtype=object), (AXIS,))


def resolve_per_device(per_device: str, mesh: Mesh) -> str:
    """``"map"`` or ``"vmap"`` for a ``per_device`` argument ("auto": map on CPU devices)."""
    if per_device not in PER_DEVICE_MODES:
        raise ValueError(f"per_device: expected one of {PER_DEVICE_MODES}, got {per_device!r}")
    if per_device != "auto":
        return per_device
    platforms = {d.platform for d in mesh.devices.flat}
    return "map" if platforms == {"cpu"} else "vmap"


def _shard_map(fn: Callable, mesh: Mesh) -> Callable:
    """``fn`` under ``shard_map`` with every argument and output split along ``AXIS``."""
    spec = PartitionSpec(AXIS)
    if hasattr(jax, "shard_map"):
        # check_vma off: the library's loops start from constants (e.g. kselect's bit search)
        # that the per-device values then make "varying"; the program is the same either way.
        return jax.shard_map(fn, mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False)
    from jax.experimental.shard_map import shard_map  # older JAX

    return shard_map(fn, mesh=mesh, in_specs=spec, out_specs=spec, check_rep=False)


def per_device(fn: Callable, mesh: Mesh, mode: str) -> Callable:
    """``fn`` (one seed's arguments -> outputs) over a leading seed axis split across the
    mesh's devices: each device runs its share by ``lax.map`` (mode "map") or ``vmap``
    ("vmap"). Not jitted; every argument and output leaf has the seed axis first, and its
    length must be a multiple of the device count."""
    if mode == "map":
        def local(*args):
            return jax.lax.map(lambda a: fn(*a), args)
    elif mode == "vmap":
        local = jax.vmap(fn)
    else:
        raise ValueError(f"mode: expected 'map' or 'vmap', got {mode!r}")
    return _shard_map(local, mesh)


@functools.lru_cache(maxsize=32)
def _compiled(train_fn: Callable, mesh: Mesh, mode: str):
    """The jitted per-device program and its input sharding (cached per train_fn, mesh, mode)."""
    sharding = NamedSharding(mesh, PartitionSpec(AXIS))
    fn = _jit(per_device(train_fn, mesh, mode), in_shardings=sharding, out_shardings=sharding)
    return fn, sharding


@functools.lru_cache(maxsize=32)
def _with_typed_keys(train_fn: Callable, impl: Any) -> Callable:
    """``train_fn`` taking raw key data of ``impl`` instead of typed keys (host-side arrays of
    typed keys cannot cross processes)."""
    return lambda data, *args: train_fn(jax.random.wrap_key_data(data, impl=impl), *args)


def global_put(tree: Any, sharding: NamedSharding) -> Any:
    """Host arrays, equal on every process, as arrays split by ``sharding``: across processes
    each process places only its own devices' slices (no data crosses the network)."""
    if jax.process_count() == 1:
        return jax.device_put(tree, sharding)

    def put(x):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])

    return jax.tree_util.tree_map(put, tree)


def gather(tree: Any) -> Any:
    """Every leaf whole, as NumPy arrays, on every process (across processes: an all-gather)."""
    if jax.process_count() == 1:
        return jax.device_get(tree)
    from jax.experimental import multihost_utils

    from hedger_jax.distributed import barrier

    barrier("gather")             # the processes finish their shares at different times
    return multihost_utils.process_allgather(tree, tiled=True)


def _pad_members(tree: Any, n: int, to: int) -> Any:
    """Each leaf's leading member axis, n long, padded to ``to`` by repeating the last member."""
    if to == n:
        return tree
    return jax.tree_util.tree_map(
        lambda x: np.concatenate([x, np.repeat(x[-1:], to - n, axis=0)]), tree)


def member_order(total: int, n_devices: int) -> np.ndarray:
    """(total,) the member at each position of a sweep's device-split axis, so that device d
    runs members d, d + n_devices, ...: neighbouring members (often one setting's seeds, of
    equal cost) are spread over the devices, which then finish together. total must be a
    multiple of n_devices."""
    return np.arange(total).reshape(total // n_devices, n_devices).T.reshape(-1)


class _Constant:
    """A NumPy array that hashes by value (a sweep's shared setting, baked into its program)."""

    def __init__(self, value: np.ndarray):
        self.value = value
        self._key = (value.dtype.str, value.shape, value.tobytes())

    def __hash__(self):
        return hash(self._key)

    def __eq__(self, other):
        return isinstance(other, _Constant) and self._key == other._key


@functools.lru_cache(maxsize=32)
def with_shared_settings(fn: Callable, treedef: Any, constants: Tuple) -> Callable:
    """``fn(x, params)`` as ``g(x, varying leaves)``: the params rebuilt from the leaves that
    vary between members and ``constants`` ((leaf index, _Constant), ...; ``shared_settings``),
    the leaves every member shares, which enter the program as constants. Cached, so equal
    arguments give the same g (and reuse its compiled programs)."""
    fixed = {i: c.value for i, c in constants}

    def g(x, varying):
        it = iter(varying)
        leaves = [fixed[i] if i in fixed else next(it) for i in range(treedef.num_leaves)]
        return fn(x, jax.tree_util.tree_unflatten(treedef, leaves))

    return g


def _same_for_all(x: np.ndarray) -> bool:
    """Whether every member (leading axis) of x holds the same value (NaN equal to NaN)."""
    return bool(np.array_equal(x, np.broadcast_to(x[:1], x.shape),
                               equal_nan=np.issubdtype(x.dtype, np.inexact)))


def shared_settings(params: Any):
    """(treedef, constants, varying) of params, a pytree whose leaves have a leading member
    axis: constants ((leaf index, value), ...) hold the leaves every member shares, in the
    form that ``with_shared_settings`` bakes into a program; varying lists the other leaves'
    indices, the program's inputs."""
    leaves, treedef = jax.tree_util.tree_flatten(params)
    leaves = [np.asarray(leaf) for leaf in leaves]
    shared = [_same_for_all(x) for x in leaves]
    constants = tuple((i, _Constant(x[0])) for i, (x, c) in enumerate(zip(leaves, shared)) if c)
    return treedef, constants, [i for i, c in enumerate(shared) if not c]


def prepare_sweep(train_fn: Callable, keys: Any, params: Any, n_devices: int):
    """What ``sweep`` runs: (fn, args, back). fn: one member's function of args (a key and the
    varying settings); args: host arrays with the member axis padded to a multiple of
    n_devices and dealt to the devices in turn (``member_order``); back: (members,) each
    member's position in the outputs.

    Settings every member shares are baked into fn as constants, the rest stay traced: a
    program whose every setting is traced compiles about twice as long and runs 1.3-1.8x
    slower than one with constants (docs/performance.md).
    """
    if not isinstance(keys, jax.Array):
        keys = jnp.asarray(keys)
    if keys.ndim < 1 or keys.shape[0] < 1:
        raise ValueError(f"keys: need a leading member axis with at least one member, got "
                         f"shape {keys.shape}")
    n = keys.shape[0]
    fn = train_fn
    if jax.dtypes.issubdtype(keys.dtype, jax.dtypes.prng_key):
        fn = _with_typed_keys(train_fn, jax.random.key_impl(keys))
        keys = jax.random.key_data(keys)
    args = (np.asarray(keys),)
    if params is not None:
        for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
            shape = np.shape(leaf)
            if not shape or shape[0] != n:
                raise ValueError(f"params{jax.tree_util.keystr(path)}: every leaf needs the "
                                 f"leading member axis of length {n} (as the keys), got "
                                 f"shape {shape}")
        treedef, constants, varying = shared_settings(params)
        fn = with_shared_settings(fn, treedef, constants)
        leaves = jax.tree_util.tree_leaves(params)
        args += ([np.asarray(leaves[i]) for i in varying],)
    total = n + (-n) % n_devices
    order = member_order(total, n_devices)
    args = jax.tree_util.tree_map(lambda x: x[order], _pad_members(args, n, total))
    return fn, args, np.argsort(order)[:n]


def sweep(train_fn: Callable, keys: Any, params: Any = None, *,
          devices: Optional[Sequence[Any]] = None, per_device: str = "auto") -> Any:
    """Run ``train_fn`` for every member of a sweep, the fast way for the devices there are.

    train_fn: ``key -> outputs``, or ``(key, params) -> outputs`` when ``params`` is given
    (e.g. ``make_train(...).train`` with a ``HedgerParams`` of per-member settings).
    keys: (members, ...) raw or typed PRNG keys. params: a pytree whose every leaf has the
    leading member axis, or None. devices: default every device of every process.

    The members are dealt to the devices in turn (a 1-D mesh ``"seeds"``; padded to a
    multiple of the device count by repeating the last member); each device runs its share
    one after another on a CPU (``per_device="map"``: each member is the single-member
    program, so its numbers do not depend on the split) and vmapped on an accelerator
    ("vmap"), "auto" choosing. Settings that every member shares enter the program as
    constants (``prepare_sweep``). On a CPU, split it into one device per core first with
    ``hedger_jax.cpu.configure(host_devices=N)``; across processes (``hedger_jax.distributed``)
    every process calls ``sweep`` with the same arguments and runs its own devices' members.

    Returns the outputs, leading axis ``members``, in the members' order: in one process JAX
    arrays (left on the devices); across processes NumPy arrays, gathered to every process.
    One compile per (train_fn, shared settings, devices, mode, members).
    """
    mesh = seed_mesh(devices)
    fn, args, back = prepare_sweep(train_fn, keys, params, mesh.devices.size)
    program, sharding = _compiled(fn, mesh, resolve_per_device(per_device, mesh))
    placed = global_put(args, sharding)
    if jax.process_count() == 1:
        return _take_members(program(*placed), back)
    from hedger_jax.distributed import compile_shared

    program = compile_shared(program, *placed)    # compiled once, by process 0
    return jax.tree_util.tree_map(lambda x: x[back], gather(program(*placed)))


@_jit
def _take_members(tree: Any, index: jax.Array) -> Any:
    """Every leaf's rows ``index`` (the members back in their order, padding dropped)."""
    return jax.tree_util.tree_map(lambda x: x[index], tree)


def shard_seeds(train_fn: Callable, keys: jax.Array, devices: Optional[Sequence[Any]] = None,
                per_device: str = "auto"):
    """``sweep(train_fn, keys, devices=devices, per_device=per_device)``: ``train_fn`` (key ->
    pytree) for every key, the seeds split across the devices."""
    return sweep(train_fn, keys, devices=devices, per_device=per_device)
