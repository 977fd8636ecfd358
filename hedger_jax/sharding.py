"""Seed sweeps sharded over devices with ``jax.sharding``.

A sweep is ``jax.vmap(train)(keys)``; here the seed axis is split across devices
(``NamedSharding`` over a 1-D mesh named ``"seeds"``), so each device runs its share of the
seeds of the same jitted program. ::

    train = make_train(env, config, run).train
    state, results = shard_seeds(train, jax.random.split(key, 64))       # all devices

Every output leaf keeps the leading seed axis and stays sharded over the devices (call
``jax.device_get`` to gather). The number of seeds need not divide the device count: the keys
are padded by repeating the last one and the padding is cut from the outputs. On CPU, test it
with ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (set before jax is imported).
"""
from __future__ import annotations

import functools
from typing import Any, Callable, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

AXIS = "seeds"


def seed_mesh(devices: Optional[Sequence[Any]] = None) -> Mesh:
    """A 1-D mesh (axis ``"seeds"``) over ``devices`` (default: all of ``jax.devices()``)."""
    devs = list(jax.devices() if devices is None else devices)
    if not devs:
        raise ValueError("devices: need at least one device")
    return Mesh(np.asarray(devs, dtype=object), (AXIS,))


@functools.lru_cache(maxsize=32)
def _compiled(train_fn: Callable, mesh: Mesh, donate: bool):
    sharding = NamedSharding(mesh, PartitionSpec(AXIS))
    return jax.jit(jax.vmap(train_fn), in_shardings=sharding, out_shardings=sharding,
                   donate_argnums=(0,) if donate else ()), sharding


def sharded_train(train_fn: Callable, devices: Optional[Sequence[Any]] = None):
    """``keys -> outputs``: the jitted, vmapped ``train_fn`` with the seed axis sharded.

    The number of seeds must be a multiple of the number of devices (``shard_seeds`` pads).
    """
    fn, sharding = _compiled(train_fn, seed_mesh(devices), False)

    def run(keys):
        return fn(jax.device_put(keys, sharding))

    return run


def shard_seeds(train_fn: Callable, keys: jax.Array, devices: Optional[Sequence[Any]] = None):
    """Run ``jax.vmap(train_fn)(keys)`` with the seed axis split across ``devices``.

    train_fn: key -> pytree (e.g. ``make_train(...).train``); keys: (n_seeds, ...) raw or typed
    PRNG keys. Returns the vmapped outputs (leading axis n_seeds), sharded over the devices.
    Recompiles only for a new (train_fn, devices, n_seeds) combination.
    """
    mesh = seed_mesh(devices)
    n_dev = mesh.devices.size
    keys = jnp.asarray(keys) if not isinstance(keys, jax.Array) else keys
    n = keys.shape[0]
    if n < 1:
        raise ValueError("keys: need at least one seed")
    pad = (-n) % n_dev
    if pad:
        keys = jnp.concatenate([keys, jnp.repeat(keys[-1:], pad, axis=0)])
    out = sharded_train(train_fn, list(mesh.devices.flat))(keys)
    if pad:
        out = jax.tree_util.tree_map(lambda x: x[:n], out)
    return out
