"""The named errors of hedger-jax, in one module that imports nothing else of the package."""


class StaticFieldError(TypeError):
    """A static setting (a ``HedgerConfig`` or ``RunConfig`` field) was given a traced value,
    e.g. by ``jax.vmap`` over a function that builds the config."""


class InvalidParamsError(ValueError):
    """A ``HedgerParams`` value is out of its range or beyond what the static config allows."""


class InvalidInputError(ValueError):
    """An input at the host boundary has the wrong shape or dtype, is NaN/inf, or is outside
    the allowed set. The message names the argument, the problem and the offending value."""


class MemoryFullError(RuntimeError):
    """The memory was full under ``full_policy="error"`` and a point was dropped."""


class NonFiniteValueError(FloatingPointError):
    """A NaN or inf tried to enter the memory; it was dropped and flagged."""


class CheckpointError(ValueError):
    """A checkpoint file is missing, truncated, corrupt, of another format or version, or does
    not match what the caller expects (config fields, env)."""
