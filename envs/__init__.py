"""JAX-native environments for HEDGER: mountain car and a simulated corridor robot.

The functional API (``reset``/``step`` pure functions over params/state pytrees) is described
in ``envs.base``. Gymnasium ids are registered by importing ``envs.gym_adapter``; the Brax
adapter lives in ``envs.brax_adapter`` (the only module that imports brax). Nothing here
imports ``hedger_jax``.
"""
from envs.spaces import ActionSpace
from envs.base import FunctionalEnv

__all__ = ["ActionSpace", "FunctionalEnv", "make", "NAMES"]

#: Every name ``make`` accepts.
NAMES = ("mountain_car_discrete", "mountain_car", "MountainCar", "mountain_car_continuous",
         "corridor")


def make(name: str, **kwargs):
    """Build a functional environment by name.

    Names: ``"mountain_car_discrete"``, ``"mountain_car_continuous"``, ``"corridor"``.
    """
    if name in ("mountain_car_discrete", "mountain_car", "MountainCar"):
        from envs.mountain_car import MountainCar
        return MountainCar(continuous=False, **kwargs)
    if name in ("mountain_car_continuous",):
        from envs.mountain_car import MountainCar
        return MountainCar(continuous=True, **kwargs)
    if name in ("corridor",):
        from envs.corridor import Corridor
        return Corridor(**kwargs)
    raise ValueError(f"unknown environment {name!r}; known: mountain_car_discrete, "
                     "mountain_car_continuous, corridor")
