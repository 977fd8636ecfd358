"""hedger-jax: HEDGER (Smart & Kaelbling, ICML 2000) as pure, jittable, vmappable JAX functions.

Core API::

    config = HedgerConfig(state_dim=2, discrete_actions=((-1.,), (0.,), (1.,)), ...)
    memory = init_memory(config)
    value, known, n = predict(config, memory, state, action)        # Algorithm 1
    action, value, known = greedy_action(config, memory, state, key)
    memory, info = train_episode(config, memory, episode)           # Algorithm 2, reversed
    memory = backup_memory(config, memory)     # every stored point again (backup_sweeps > 0)

Every function with a ``params`` argument (these three among them) takes a ``HedgerParams``
of traced hyperparameters (vmap over it for a sweep) or, by default, None for the config's
values. ``make_train`` builds a whole run as one
pure function; ``Hedger`` is the host-side learner.

Importing it changes nothing global. ``hedger_jax.jit`` is ``jax.jit`` with HEDGER's
per-program XLA options; ``hedger_jax.cpu.configure()`` tunes the whole process for CPU speed
(call it before any JAX computation). ``sweep(train, keys, params)`` runs a sweep's members
split over every device, of every process once ``hedger_jax.distributed.initialize()`` ran.
"""
from hedger_jax import cpu, distributed
from hedger_jax.cpu import jit
from hedger_jax.config import HedgerConfig, StaticFieldError
from hedger_jax.presets import ADAPTIVE, ADAPTIVE_CONTINUOUS, TASK
from hedger_jax.params import HedgerParams, InvalidParamsError, check_params
from hedger_jax.greedy import greedy_action, greedy_value, maximise_1d
from hedger_jax.memory import (FLAG_FULL, FLAG_NONFINITE, Memory, MemoryFullError,
                               NonFiniteValueError, add_points, init_memory, memory_check,
                               select_neighbours, stored_points)
from hedger_jax.prediction import Prediction, predict, predict_detailed
from hedger_jax.train import TrainInfo, Transition, train_episode, train_step
from hedger_jax.backup import BackupPlan, backup_memory, backup_plan, backup_with_plan
from hedger_jax.agent import RunConfig, make_train, transitions_from_demonstrations
from hedger_jax.checkpoint import (Checkpoint, CheckpointError, load_checkpoint,
                                   read_checkpoint_header, save_checkpoint)
from hedger_jax.learner import Hedger, make_env
from hedger_jax.validation import InvalidInputError
from hedger_jax.sharding import sweep

from hedger_jax.version import __version__

__all__ = [
    "ADAPTIVE", "ADAPTIVE_CONTINUOUS", "TASK", "HedgerConfig", "HedgerParams", "InvalidParamsError", "StaticFieldError", "check_params",
    "Memory", "MemoryFullError", "NonFiniteValueError", "FLAG_FULL",
    "FLAG_NONFINITE", "init_memory", "add_points", "memory_check", "select_neighbours",
    "stored_points", "Prediction", "predict", "predict_detailed", "greedy_action",
    "greedy_value", "maximise_1d", "Transition", "TrainInfo", "train_step", "train_episode",
    "backup_memory", "backup_plan", "backup_with_plan", "BackupPlan",
    "RunConfig", "make_train", "transitions_from_demonstrations", "Hedger", "make_env",
    "Checkpoint", "CheckpointError", "save_checkpoint", "load_checkpoint",
    "read_checkpoint_header", "InvalidInputError", "cpu", "distributed", "jit", "sweep",
    "__version__",
]
