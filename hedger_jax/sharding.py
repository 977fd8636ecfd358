"""Seed sweeps split over devices.

Each device runs its share of the seeds inside one jitted program (``jax.shard_map`` over a
1-D mesh named ``"seeds"``)::

    train = make_train(env, config, run).train
    state, results = shard_seeds(train, jax.random.split(key, 64))       # all devices

Within a device the seeds run either vmapped (``per_device="vmap"``: one batched program, what
a GPU wants) or one after another (``"map"``: ``lax.map``, the single-seed program in a loop).
``"auto"`` (default) picks ``"map"`` on CPU devices and ``"vmap"`` on accelerators. Why: on a
CPU a vmapped episode loop runs until its longest member ends and the batched index and fit
kernels cost about as much per seed as one seed's, so vmapped seeds add no throughput, while
``map`` keeps every seed at the single-seed rate and the devices run side by side.

Every output leaf keeps the leading seed axis and stays sharded over the devices (call
``jax.device_get`` to gather). The number of seeds need not divide the device count: the keys
are padded by repeating the last one and the padding is cut from the outputs. A seed's result
does not depend on the device it ran on or on how many others shared it (``"map"``: the
single-seed program; ``"vmap"``: as ``jax.vmap(train_fn)``). On a CPU, split it into N
devices with ``hedger_jax.cpu.configure(host_devices=N)`` before JAX starts.
"""
from __future__ import annotations

import functools
from typing import Any, Callable, Optional, Sequence

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


def sharded_train(train_fn: Callable, devices: Optional[Sequence[Any]] = None,
                  per_device: str = "auto"):
    """``keys -> outputs``: ``train_fn`` over the seed axis of keys, split across ``devices``
    (see ``shard_seeds``). The number of seeds must be a multiple of the number of devices
    (``shard_seeds`` pads)."""
    mesh = seed_mesh(devices)
    mode = resolve_per_device(per_device, mesh)
    fn, sharding = _compiled(train_fn, mesh, mode)

    def run(keys):
        return fn(jax.device_put(keys, sharding))

    return run


def shard_seeds(train_fn: Callable, keys: jax.Array, devices: Optional[Sequence[Any]] = None,
                per_device: str = "auto"):
    """Run ``train_fn`` for every key, the seeds split across ``devices``.

    train_fn: key -> pytree (e.g. ``make_train(...).train``); keys: (n_seeds, ...) raw or typed
    PRNG keys. per_device: "auto" | "map" | "vmap" (module doc). Returns the outputs with
    leading axis n_seeds, sharded over the devices. Compiles once per (train_fn, devices,
    mode, n_seeds).
    """
    mesh = seed_mesh(devices)
    n_dev = mesh.devices.size
    keys = jnp.asarray(keys) if not isinstance(keys, jax.Array) else keys
    if keys.ndim < 1 or keys.shape[0] < 1:
        raise ValueError(f"keys: need a leading seed axis with at least one seed, got shape "
                         f"{keys.shape}")
    n = keys.shape[0]
    pad = (-n) % n_dev
    if pad:
        keys = jnp.concatenate([keys, jnp.repeat(keys[-1:], pad, axis=0)])
    out = sharded_train(train_fn, list(mesh.devices.flat), per_device)(keys)
    if pad:
        out = jax.tree_util.tree_map(lambda x: x[:n], out)
    return out
