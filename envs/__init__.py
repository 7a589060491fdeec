"""Goal-conditioned maze environments: the MJX ant and its pure-JAX point-mass twin.

    env = envs.make("u_maze")                 # MJX ant (29-d obs, 8 actions)
    env = envs.make("point_u_maze")           # point mass (4-d obs, 2 actions)
    env = envs.make("u_maze", robot="point")  # same
    env = envs.make_from_map("1111\\n1rg1\\n1111", cell_size=2.0, robot="point")

Overrides: any field of the robot's config (`AntConfig` / `PointConfig`, e.g. episode_length,
goal_tolerance, start_margin) plus `start_xy=(x, y)` / `goal_xy=(x, y)` to move the task start/goal.
"""
from __future__ import annotations

import dataclasses

from dscpp_jax.envs._quiet_import import import_quietly

import_quietly("mujoco.mjx")  # first, before brax imports it: no notice about the optional Warp back end

from dscpp_jax.envs.goals import (EPISODE_LENGTH, GOAL_TOLERANCE, achieved_goal, goal_reached,  # noqa: F401
                        goal_reward)
from dscpp_jax.envs.maze_layout import BUILTIN_MAPS, MazeLayout, get_layout, parse_map  # noqa: F401
from dscpp_jax.envs.point_maze import PointConfig, PointMazeEnv  # noqa: F401

ANT_NAMES = tuple(BUILTIN_MAPS)  # u_maze, medium, large, four_rooms, ant_reacher
POINT_NAMES = tuple("point_" + n for n in ANT_NAMES)
ENV_NAMES = ANT_NAMES + POINT_NAMES
ROBOTS = ("ant", "point")


def _build(layout: MazeLayout, robot: str, overrides: dict):
    if robot not in ROBOTS:
        raise ValueError(f"unknown robot {robot!r}; valid robots: {list(ROBOTS)}")
    if robot == "point":
        cfg_cls, env_cls = PointConfig, PointMazeEnv
    else:
        from dscpp_jax.envs.ant_maze import AntConfig, AntMazeEnv
        cfg_cls, env_cls = AntConfig, AntMazeEnv
    fields = {f.name for f in dataclasses.fields(cfg_cls)}
    bad = sorted(set(overrides) - fields)
    if bad:
        raise ValueError(f"unknown override(s) {bad} for robot {robot!r}; valid: "
                         f"{sorted(fields | {'start_xy', 'goal_xy', 'robot'})}")
    _check_overrides(cfg_cls, overrides)
    return env_cls(layout, cfg_cls(**overrides))


# overrides that must be positive (a zero-length episode or a negative tolerance would compile
# into an env that never ends or never succeeds)
_POSITIVE = ("episode_length", "goal_tolerance", "dt", "timestep", "frame_skip", "substeps",
             "solver_iterations", "ls_iterations")


def _check_overrides(cfg_cls, overrides: dict) -> None:
    """Each override has its field's type (an int where the default is an int, ...) and the
    lengths, steps and tolerances are positive; a ValueError names the field and an example."""
    import math
    import numbers
    defaults = cfg_cls()
    for k, v in overrides.items():
        d = getattr(defaults, k)
        if isinstance(d, bool):
            ok = isinstance(v, bool)
        elif isinstance(d, int):
            ok = isinstance(v, numbers.Integral) and not isinstance(v, bool)
        elif isinstance(d, float):
            ok = isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)
        elif isinstance(d, str):
            ok = isinstance(v, str)
        else:
            ok = True
        if not ok:
            raise ValueError(f"{cfg_cls.__name__}.{k} must be {type(d).__name__} like its default "
                             f"{d!r}, got {v!r}")
        if k in _POSITIVE and not v > 0:
            raise ValueError(f"{cfg_cls.__name__}.{k} must be > 0, got {v!r} (default {d!r})")


def make(name: str, **overrides):
    """An env by name (see ENV_NAMES). `robot="point"|"ant"` picks the robot for a layout name."""
    robot = overrides.pop("robot", None)
    start_xy = overrides.pop("start_xy", None)
    goal_xy = overrides.pop("goal_xy", None)
    if not isinstance(name, str) or name not in ENV_NAMES:
        raise ValueError(f"unknown env name {name!r}; valid names: {list(ENV_NAMES)}")
    if name.startswith("point_"):
        if robot not in (None, "point"):
            raise ValueError(f"env {name!r} is a point-mass env but robot={robot!r} was given; "
                             f"use {name[len('point_'):]!r} for the ant")
        name, robot = name[len("point_"):], "point"
    robot = robot or "ant"
    layout = get_layout(name, start_xy=start_xy, goal_xy=goal_xy)
    return _build(layout, robot, overrides)


def make_from_map(map_text: str, cell_size: float, robot: str = "ant", name: str = "custom",
                  **overrides):
    """An env on a user text map ('1'/'#' wall, '0'/'.' free, 'r' start, 'g' goal; one line per row)."""
    start_xy = overrides.pop("start_xy", None)
    goal_xy = overrides.pop("goal_xy", None)
    if robot not in ROBOTS:
        raise ValueError(f"unknown robot {robot!r}; valid robots: {list(ROBOTS)}")
    layout = parse_map(map_text, cell_size, name=name, start_xy=start_xy, goal_xy=goal_xy)
    return _build(layout, robot, overrides)
