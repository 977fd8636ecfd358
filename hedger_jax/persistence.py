"""``Hedger.save`` / ``Hedger.load``: a learner in one checkpoint file (``hedger_jax.checkpoint``:
atomic, checksummed).

Beside the config, run config and memory the file holds, as extra arrays, ``key`` (raw uint32
(2,)), ``counters`` int64 (3,) (``num_timesteps``, ``num_demo_timesteps``, ``num_episodes``)
and ``env_params/<i>`` (the env params' leaves in ``tree_leaves`` order), and in its metadata
what rebuilds the env: ``env_name``, ``env_kwargs``, ``env_max_steps``, ``chunk_episodes``,
``n_env_params``, ``host_loop`` and ``env_from_instance``.
"""
from __future__ import annotations

import os
from typing import Any, Dict, Optional, Union

import jax
import jax.numpy as jnp
import numpy as np

from hedger_jax import environments
from hedger_jax.checkpoint import (Checkpoint, CheckpointError, load_checkpoint,
                                   save_checkpoint)
from hedger_jax.config import HedgerConfig
from hedger_jax.validation import check_key

__all__ = ["save", "load"]

PathLike = Union[str, os.PathLike]


def save(model: Any, path: PathLike) -> str:
    """Write the ``Hedger`` ``model`` to ``path`` -> the path."""
    leaves = jax.tree_util.tree_leaves(model.env_params)
    extra = {"key": np.asarray(model.key),
             "counters": np.asarray([model.num_timesteps, model.num_demo_timesteps,
                                     model.num_episodes], np.int64)}
    for i, leaf in enumerate(leaves):
        extra[f"env_params/{i}"] = np.asarray(leaf)
    meta = {"env_name": model._env_name, "env_kwargs": model.env_kwargs,
            "env_max_steps": int(model.env.max_steps), "chunk_episodes": model.chunk_episodes,
            "n_env_params": len(leaves), "host_loop": model.host_loop,
            "env_from_instance": model._from_instance}
    return save_checkpoint(path, model.config, model.memory, model.run_config, seed=model.seed,
                           env_id=model.env_id, extra_arrays=extra, metadata=meta)


def load(cls: type, path: PathLike, env: Any = None, *, env_params: Any = None,
         config: Optional[HedgerConfig] = None) -> Any:
    """A ``cls`` (``Hedger``) learner restored from ``path``; see ``Hedger.load``."""
    ck = load_checkpoint(path, config=config)
    meta = ck.metadata
    env = _stored_env(meta, path) if env is None else env
    by_id = isinstance(env, str)
    model = cls(env, ck.config, ck.run_config, seed=meta.get("seed") or 0,
                env_kwargs=_env_kwargs(meta, env) if by_id else None,
                chunk_episodes=int(meta.get("chunk_episodes", 10)), env_params=env_params)
    if by_id:
        model.env_kwargs = dict(meta.get("env_kwargs") or {})
    if env_params is None:
        model.env_params = _stored_env_params(ck, model.env_params, path)
    model.memory = ck.memory
    if "key" in ck.extra_arrays:
        model.key = jnp.asarray(check_key(ck.extra_arrays["key"], "stored key"))
    if "counters" in ck.extra_arrays:
        c = [int(x) for x in ck.extra_arrays["counters"]]
        model.num_timesteps, model.num_demo_timesteps, model.num_episodes = c
    return model


def _stored_env(meta: Dict[str, Any], path: PathLike) -> str:
    """The env id to rebuild the env from; refused where an id cannot rebuild it."""
    env_id = meta.get("env_id")
    if meta.get("host_loop") and meta.get("env_from_instance"):
        raise CheckpointError(f"checkpoint {os.fspath(path)!r}: the learner was built from a "
                              f"Gymnasium env instance ({env_id or 'no id'}); pass env= (an "
                              "env like it) to load it")
    if env_id is None:
        raise CheckpointError(f"checkpoint {os.fspath(path)!r}: no env id stored; pass env=")
    return env_id


def _env_kwargs(meta: Dict[str, Any], env_id: str) -> Dict[str, Any]:
    """The stored ``env_kwargs``, and for a project env the stored episode cap."""
    kwargs = dict(meta.get("env_kwargs") or {})
    if environments.is_functional_name(env_id) and "max_steps" not in kwargs \
            and meta.get("env_max_steps") is not None:
        kwargs["max_steps"] = meta["env_max_steps"]
    return kwargs


def _stored_env_params(ck: Checkpoint, current: Any, path: PathLike) -> Any:
    """The stored env params in the structure of ``current`` (the env's params); ``current``
    when none were stored. Raises ``CheckpointError`` when they do not fit."""
    n = int(ck.metadata.get("n_env_params", 0))
    leaves, treedef = jax.tree_util.tree_flatten(current)
    stored = [ck.extra_arrays.get(f"env_params/{i}") for i in range(n)]
    if n == len(leaves) and all(s is not None and np.shape(s) == np.shape(l)
                                for s, l in zip(stored, leaves)):
        return jax.tree_util.tree_unflatten(treedef, [jnp.asarray(s) for s in stored])
    if n:
        raise CheckpointError(f"checkpoint {os.fspath(path)!r}: the stored env params ({n} "
                              f"leaves) do not fit the env's params ({len(leaves)} leaves); "
                              "pass env_params=")
    return current
