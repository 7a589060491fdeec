"""Robust Deep Skill Chaining (DSC++) end to end in JAX.

    import jax, dscpp_jax
    cfg = dscpp_jax.preset("fast", env="point_u_maze", algo="mb_dscpp")
    state = dscpp_jax.init(jax.random.PRNGKey(0), cfg)
    for _ in range(10):
        state, metrics = dscpp_jax.train_step(state)      # jitted, compiles once
    summary, result = dscpp_jax.evaluate(state)            # jitted, no side effects
    policy = dscpp_jax.make_policy(state)                  # pure, jit-able

Many seeds in one jitted program, sharded over all devices (and hosts): see
`dscpp_jax.seed_group`:

    states = dscpp_jax.init_group([0, 1, 2, 3], cfg)       # seed s == init(PRNGKey(s), cfg)
    states, metrics = dscpp_jax.train_step_group(states)  # metrics: (4,) per key
    summaries, result = dscpp_jax.evaluate_group(states)  # one summary dict per seed
"""
from dscpp_jax import envs  # noqa: F401  (first: imports MuJoCo MJX without the missing-Warp notice)
from dscpp_jax.config import ALGOS, SUBGOALS, Config, preset
from dscpp_jax.evaluate import EvalResult, Policy, evaluate, evaluate_episodes, make_policy
from dscpp_jax.seed_group import evaluate_group, init_group, seed_mesh, seed_state, \
    train_step_group
from dscpp_jax.trainer import TrainState, init, make_env, train_step, train_step_impl

__all__ = ["ALGOS", "SUBGOALS", "Config", "preset", "TrainState", "init", "train_step",
           "train_step_impl", "evaluate", "evaluate_episodes", "EvalResult", "make_policy",
           "Policy", "make_env", "init_group", "train_step_group", "evaluate_group", "seed_state",
           "seed_mesh"]
__version__ = "0.1.0"
