"""Jitted evaluation and the policy constructor.

`evaluate(state, key, num_episodes)` runs `num_episodes` episodes in parallel from the task start
(or from given start positions) with deterministic option policies: no exploration noise, no
random actions, no example collection, no learning. The TrainState is only read, never returned,
so evaluation cannot leak into training. The episodes act through `dscpp_jax.acting`, the same
functions as training's rollout, without exploration: with one TD3 per option (the baselines'
region policies, or per-option critics) each option acts with its own actor. It reports the success rate, steps to the
goal, per-option success rates, the chain probability (paper eq. 3) and the trajectories for
plots.
"""
from __future__ import annotations

from typing import Any, Dict, NamedTuple, Optional

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from dscpp_jax import acting as A
from dscpp_jax import trainer as T
from dscpp_jax.config import Config
from dscpp_jax.td3 import td3_random_prob
from dscpp_jax.envs.goal_env import select_states
from dscpp_jax.td3 import TD3Config


@flax.struct.dataclass
class EvalResult:
    success: jax.Array        # (N,) bool: reached the task goal
    steps: jax.Array          # (N,) int32: steps taken (episode length when not reached)
    xy: jax.Array             # (L + 1, N, 2) positions; frozen after the episode ended
    option: jax.Array         # (L, N) int32 option executed at each step (-1 after the end)
    active: jax.Array         # (L, N) bool: the episode was still running at that step
    option_executions: jax.Array  # (K,) option executions that ended during evaluation
    option_successes: jax.Array   # (K,)
    option_failures: jax.Array    # (N,) int32: option executions that ended without success
    global_steps: jax.Array       # (N,) int32: steps spent in the global option
    upright: jax.Array            # (N,) float32: env.upright at the end (below 0: on its back)
    chain_probability: jax.Array  # () from the training statistics (eq. 3)
    num_options: jax.Array        # () options in the chain (including global and goal options)
    # Filled only by `evaluate_episodes(..., record=True)` (videos); None otherwise.
    obs_seq: Optional[jax.Array] = None      # (L + 1, N, obs_dim) observations, frozen after the end
    subgoal_seq: Optional[jax.Array] = None  # (L, N, 2) the running option's subgoal at each step
    qpos_seq: Optional[jax.Array] = None     # (L + 1, N, nq) MuJoCo qpos (MJX envs only)


def evaluate_episodes_impl(state: T.TrainState, key, num_episodes: int, starts=None,
                           record: bool = False, num_steps: Optional[int] = None,
                           explore: bool = False) -> EvalResult:
    """Un-jitted `evaluate_episodes`: `num_episodes` episodes of the deterministic policy (the
    acting of `dscpp_jax.acting`, as in training, without exploration or example collection).

    `record` (static) also keeps the observations, subgoals and (MJX envs) qpos of every step;
    off, the program is the same as without it. `num_steps` (static) caps the episodes at fewer
    steps than `config.task.episode_length` (an episode cut short counts as not successful).
    `explore` (static) acts with training's action noise instead of deterministically: the
    actor's Gaussian noise (model-free; no random-action schedule) or MPC with random actions at
    `random_action_prob` (model-based). A diagnostic: it tells a policy that is wrong apart from
    one that is only stuck in one deterministic motion from nearly the same start every time."""
    config: Config = state.config
    N, L, K = num_episodes, config.task.episode_length, config.chain.max_options
    env = T.make_env(config, worlds=config.run.group_size * N)
    if num_steps is not None:
        L = max(1, min(L, int(num_steps)))
    k_reset, k_run = jax.random.split(key)
    ks = jax.random.split(k_reset, N)
    if starts is None:
        es = jax.vmap(env.reset)(ks)
    else:
        es = jax.vmap(env.reset_at)(ks, jnp.asarray(starts, jnp.float32))
    goal = jnp.asarray(env.goal, jnp.float32)
    ex = A.exec_init(config, es.obs, goal)
    chain, td3, dyn, dp_table = state.chain, state.td3, state.dyn, state.dp_table

    def cond(carry):
        t, active = carry[0], carry[3]
        return (t < L) & jnp.any(active)

    def body(carry):
        (t, es, ex, active, success, steps, n_exec, n_succ, xy_buf, opt_buf, act_buf, n_fail,
         n_global, rec) = carry
        k_opt, k_act = jax.random.split(jax.random.fold_in(k_run, t))
        obs = es.obs

        # CHOOSE OPTIONS AND SUBGOALS, ACT (deterministic unless `explore`)
        ex = A.choose_options(config, env, chain, dp_table, td3, ex, obs, k_opt, active,
                              evaluation=True)
        acts = A.policy_actions(config, td3, dyn, obs, ex.subgoal, k_act, explore, 0.0,
                                ex.option)

        # STEP (finished episodes stay where they ended) AND END OPTIONS
        nes = jax.vmap(env.step)(es, acts)
        nes = select_states(active, nes, es)
        ex = A.push_traj(ex, nes.obs[:, :2])
        done = (nes.done > 0) & active
        ended, osucc = A.option_end(config, env, chain, ex, nes.obs[:, :2], done)
        ended = ended & active

        # COUNT AND RECORD (nothing is learned)
        onehot = jax.nn.one_hot(jnp.where(ended, ex.option, K), K + 1, dtype=jnp.int32)[:, :K]
        n_exec = n_exec + onehot.sum(0)
        n_succ = n_succ + (onehot * (osucc & ended)[:, None]).sum(0)
        n_fail = n_fail + (ended & ~osucc & (ex.option >= 0)).astype(jnp.int32)
        n_global = n_global + (active & (ex.option == 0)).astype(jnp.int32)
        opt_buf = opt_buf.at[t].set(jnp.where(active, ex.option, A.NO_OPTION))
        act_buf = act_buf.at[t].set(active)
        xy_buf = xy_buf.at[t + 1].set(nes.obs[:, :2])
        if record:
            rec = dict(rec, obs=rec["obs"].at[t + 1].set(nes.obs),
                       subgoal=rec["subgoal"].at[t].set(ex.subgoal))
            if "qpos" in rec:
                rec["qpos"] = rec["qpos"].at[t + 1].set(nes.pipeline_state.qpos)
        ex = ex.replace(option=jnp.where(ended, A.NO_OPTION, ex.option))
        success = success | (done & (nes.info["success"] > 0))
        steps = steps + active.astype(jnp.int32)
        active = active & ~done
        return (t + 1, nes, ex, active, success, steps, n_exec, n_succ, xy_buf, opt_buf, act_buf,
                n_fail, n_global, rec)

    z = jnp.zeros((K,), jnp.int32)
    xy0 = jnp.broadcast_to(es.obs[None, :, :2], (L + 1, N, 2))
    carry0 = (jnp.zeros((), jnp.int32), es, ex, jnp.ones((N,), bool), jnp.zeros((N,), bool),
              jnp.zeros((N,), jnp.int32), z, z, xy0, jnp.full((L, N), A.NO_OPTION, jnp.int32),
              jnp.zeros((L, N), bool), jnp.zeros((N,), jnp.int32), jnp.zeros((N,), jnp.int32),
              _record_init(es, L) if record else {})
    carry = jax.lax.while_loop(cond, body, carry0)
    t_end, es_end, _, _, success, steps, n_exec, n_succ, xy, opt, act, n_fail, n_global, rec = carry
    # positions after an episode ended stay where it ended
    xy = _freeze_after_end(xy, steps)
    rec = {k: (v if k == "subgoal" else _freeze_after_end(v, steps)) for k, v in rec.items()}
    if config.hierarchical:
        cm = A.chain_metrics(config, chain)
        cp, nopt = cm["options/chain_probability"], cm["options/num_options"]
    else:
        cp, nopt = jnp.asarray(jnp.nan), jnp.asarray(1.0)
    return EvalResult(success=success, steps=steps, xy=xy, option=opt,
                      active=act,
                      option_executions=n_exec, option_successes=n_succ,
                      option_failures=n_fail, global_steps=n_global,
                      upright=jnp.asarray(env.upright(es_end.obs), jnp.float32),
                      chain_probability=jnp.asarray(cp, jnp.float32),
                      num_options=jnp.asarray(nopt, jnp.float32),
                      obs_seq=rec.get("obs"), subgoal_seq=rec.get("subgoal"),
                      qpos_seq=rec.get("qpos"))


def _record_init(es, L: int) -> Dict[str, jax.Array]:
    """Buffers of the per-step record: row 0 holds the reset state."""
    N = es.obs.shape[0]
    rec = {"obs": jnp.broadcast_to(es.obs[None], (L + 1,) + es.obs.shape),
           "subgoal": jnp.zeros((L, N, 2), jnp.float32)}
    qpos = getattr(es.pipeline_state, "qpos", None)
    if qpos is not None:
        rec["qpos"] = jnp.broadcast_to(qpos[None], (L + 1,) + qpos.shape)
    return rec


def _freeze_after_end(seq, steps):
    """(L + 1, N, ...) rows after each episode's last step repeat that step's row."""
    idx = steps.reshape((1, -1) + (1,) * (seq.ndim - 2))
    last = jnp.take_along_axis(seq, idx, axis=0)
    after = (jnp.arange(seq.shape[0])[:, None] > steps[None, :]).reshape(seq.shape[:2] + (1,) * (seq.ndim - 2))
    return jnp.where(after, last, seq)


evaluate_episodes = jax.jit(evaluate_episodes_impl, static_argnames=("num_episodes", "record", "num_steps",
                                                         "explore"))
"""Jitted `evaluate_episodes(state, key, num_episodes, starts=None, record=False, num_steps=None,
explore=False) -> EvalResult` (`record`: also the per-step observations, subgoals and qpos, for
videos; `explore`: with training's action noise)."""


def summarize(result: EvalResult, prefix: str = "eval/") -> Dict[str, float]:
    """Host-side scalar summary of an EvalResult (namespaced for logs)."""
    succ = np.asarray(result.success)
    steps = np.asarray(result.steps)
    on_back = np.asarray(result.upright) < 0
    out = {
        f"{prefix}success_rate": float(succ.mean()),
        f"{prefix}steps_to_goal": float(steps[succ].mean()) if succ.any() else float("nan"),
        f"{prefix}chain_probability": float(result.chain_probability),
        f"{prefix}num_options": float(result.num_options),
        # why episodes fail: on its back at the end, option timeouts, time in the global option
        f"{prefix}flipped_rate": float(on_back.mean()),
        f"{prefix}flipped_failures": float((~succ & on_back).sum()),
        f"{prefix}option_failures_per_episode": float(np.asarray(result.option_failures).mean()),
        f"{prefix}global_option_share": float(np.asarray(result.global_steps).sum()
                                              / max(1, int(steps.sum()))),
    }
    ne, ns = np.asarray(result.option_executions), np.asarray(result.option_successes)
    for k in range(ne.shape[0]):
        out[f"{prefix}option_success/{k}"] = float(ns[k] / ne[k]) if ne[k] > 0 else float("nan")
    return out


def evaluate(state: T.TrainState, key: Optional[jax.Array] = None, num_episodes: Optional[int] = None,
             starts=None, explore: bool = False) -> tuple[Dict[str, float], EvalResult]:
    """Evaluate from the task start (or `starts`, (N, 2)); returns (scalar metrics, EvalResult).
    `explore`: act with training's action noise (see `evaluate_episodes_impl`), a diagnostic; the
    success figures of the library are always deterministic.

    The default key depends only on the iteration, so evaluation never consumes the training
    PRNG stream.
    """
    if not isinstance(state, T.TrainState):
        raise TypeError(f"evaluate(state, ...) needs the TrainState made by dscpp_jax.init or "
                        f"train_step, got {type(state).__name__}")
    cfg = state.config
    if starts is not None:
        shape = np.shape(starts)
        if len(shape) not in (1, 2) or shape[-1] != 2 or int(np.prod(shape)) == 0:
            raise ValueError(f"starts must be (x, y) positions, shape (N, 2) (e.g. [[8.0, 8.0], "
                             f"[0.0, 4.0]]), got shape {tuple(shape)}")
        starts = jnp.asarray(starts, jnp.float32).reshape(-1, 2)
        num_episodes = int(starts.shape[0])
    if num_episodes is not None and int(num_episodes) < 1:
        raise ValueError(f"num_episodes must be >= 1, got {num_episodes}")
    n = int(num_episodes or cfg.eval.episodes)
    if key is None:
        key = jax.random.fold_in(jax.random.PRNGKey(1_000_003),
                                 int(state.counters.iteration))
    res = evaluate_episodes(state, key, n, starts, explore=bool(explore))
    return summarize(res), res


# ------------------------------------------------------------------------------------------------
# Policy constructor
# ------------------------------------------------------------------------------------------------
class Policy(NamedTuple):
    """A deterministic DSC++ (or flat) policy over B environments.

    carry = policy.init(obs)                       # obs (B, obs_dim)
    carry, action, option = policy.step(carry, obs, key)
    All functions are pure and jit-able; the policy closes over (copies of) the learned state.
    """

    init: Any
    step: Any


def make_policy(state: T.TrainState, deterministic: bool = True) -> Policy:
    """Build a policy from a TrainState: option choice, subgoals, MPC / actor actions."""
    config = state.config
    env = T.make_env(config)
    chain, td3, dyn, dp_table = state.chain, state.td3, state.dyn, state.dp_table
    goal = jnp.asarray(env.goal, jnp.float32)
    tcfg = TD3Config.from_section(config.td3, config.model_based)

    def init(obs):
        return A.exec_init(config, obs, goal)

    def step(ex, obs, key):
        xy = obs[:, :2]
        # options that reached their subgoal region or timed out at `obs` end before acting
        ended, _ = A.option_end(config, env, chain, ex, xy, jnp.zeros(xy.shape[:1]))
        started = ex.opt_steps > 0
        ex = ex.replace(option=jnp.where(ended & started, A.NO_OPTION, ex.option))
        k_opt, k_act = jax.random.split(key)
        ex = A.choose_options(config, env, chain, dp_table, td3, ex, obs, k_opt,
                              evaluation=deterministic)
        p = (A.random_action_probs(config, chain, ex.option, state.counters.option_successes)
             if config.exploration_per_option else td3_random_prob(tcfg,
                                                                   state.counters.option_successes))
        acts = A.policy_actions(config, td3, dyn, obs, ex.subgoal, k_act, not deterministic, p,
                                ex.option)
        ex = ex.replace(opt_steps=ex.opt_steps + 1)
        return ex, acts, ex.option

    return Policy(init=init, step=step)
