"""hedger-jax: HEDGER (Smart & Kaelbling, ICML 2000) as pure, jittable, vmappable JAX functions.

Core API::

    config = HedgerConfig(state_dim=2, discrete_actions=((-1.,), (0.,), (1.,)), ...)
    memory = init_memory(config)
    value, known, n = predict(config, memory, state, action)        # Algorithm 1
    action, value, known = greedy_action(config, memory, state, key)
    memory, info = train_episode(config, memory, episode)           # Algorithm 2, reversed

Importing this package is light: it never imports brax. It appends
``--xla_cpu_enable_concurrency_optimized_scheduler=false`` to ``XLA_FLAGS`` (an XLA CPU
deadlock seen in large vmapped programs; see ``hedger_jax.runtime`` for why and how to opt
out), and offers ``serial_codegen`` for compiling training loops over large memories (see
``hedger_jax.runtime``).
"""
from hedger_jax.runtime import apply_safe_cpu_flags as _apply_safe_cpu_flags

_apply_safe_cpu_flags()

from hedger_jax.config import HedgerConfig
from hedger_jax.greedy import greedy_action, greedy_value, maximise_1d
from hedger_jax.memory import (FLAG_FULL, FLAG_NONFINITE, Memory, MemoryFullError,
                               NonFiniteValueError, add_points, init_memory, memory_check,
                               select_neighbours, stored_points)
from hedger_jax.predict import Prediction, predict, predict_detailed
from hedger_jax.train import TrainInfo, Transition, train_episode, train_step
from hedger_jax.agent import RunConfig, make_train, transitions_from_demonstrations
from hedger_jax.checkpoint import (Checkpoint, CheckpointError, load_checkpoint,
                                   read_checkpoint_header, save_checkpoint)
from hedger_jax.learner import Hedger, make_env
from hedger_jax.validation import InvalidInputError
from hedger_jax.runtime import jit_serial_codegen, serial_codegen

__version__ = "0.2.0"

__all__ = [
    "HedgerConfig", "Memory", "MemoryFullError", "NonFiniteValueError", "FLAG_FULL",
    "FLAG_NONFINITE", "init_memory", "add_points", "memory_check", "select_neighbours",
    "stored_points", "Prediction", "predict", "predict_detailed", "greedy_action",
    "greedy_value", "maximise_1d", "Transition", "TrainInfo", "train_step", "train_episode",
    "RunConfig", "make_train", "transitions_from_demonstrations", "Hedger", "make_env",
    "Checkpoint", "CheckpointError", "save_checkpoint", "load_checkpoint",
    "read_checkpoint_header", "InvalidInputError", "serial_codegen", "jit_serial_codegen",
    "__version__",
]
