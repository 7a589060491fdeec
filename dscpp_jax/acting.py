"""Acting in the environment: the per-step logic of the paper's Algorithm 2 (ROLLOUT), shared by
training's rollout (`trainer.rollout`), in-band evaluation (`inband_act`, `inband_record`) and
separate evaluation (`dscpp_jax.evaluate`), as Brax's ``acting.py`` serves its trainers and its
evaluator.

One environment step of a batch of B environments, in the paper's words::

    ex   = choose_options(...)      # Alg. 2 l. 4-5: o = pi_O(s_t) where none runs, g ~ beta_o
    a    = policy_actions(...)      # Alg. 2 l. 6: pi_o(. | g): MPC (eq. 2) or the TD3 actor
    ...  the env steps ...
    ex   = push_traj(ex, xy')       # the option's trajectory (its last `buffer_len` positions)
    ended, success = option_end(...)  # Alg. 2 l. 7: s reached g inside beta_o, timeout, episode end
    chain = record_outcomes(...)    # Alg. 2 l. 8-11: positive / negative examples (training only)

Training explores (Gaussian actor noise and random actions, or random actions around MPC);
evaluation acts deterministically and records nothing. Every function is pure and shape-stable;
the run's `Config` is a static argument, the env an object whose constants are closed over.

Also here: the value function V(s | g) of the shared (or an option's) critic that MPC and the DP
subgoals query; and the seed-group predicates (`any_seed`, `all_seeds`) that keep work off runs of a vmapped seed group that do not need it.
"""
from __future__ import annotations

from typing import Any, Dict

import flax.struct
import jax
import jax.numpy as jnp

from dscpp_jax import frontier, subgoals
from dscpp_jax.config import Config
from dscpp_jax.dynamics import DynamicsConfig
from dscpp_jax.mpc import MPCConfig, mpc_actions as _mpc_shooting, td3_value_net
from dscpp_jax.options import chain_metrics as _chain_metrics, option_terminates, record_outcomes \
    as _record_outcomes, select_option, table_columns, TABLE_PREFIX
from dscpp_jax.td3 import TD3Config, td3_act, td3_explore, td3_option, td3_perturb, \
    td3_random_prob, td3_value
from dscpp_jax.envs.goal_env import select_states

PyTree = Any
NO_OPTION = -1
GLOBAL_OPTION = 0
GOAL_OPTION = 1

FRONTIER_KEY_SALT = 0xF0_27E1
"""The iteration's key folded with this gives the frontier candidates' key (dscpp_jax.frontier),
off the keys the rest of the iteration splits, so runs without the frontier are unchanged."""


# ------------------------------------------------------------------------------------------------
# State of the options running in a batch of environments
# ------------------------------------------------------------------------------------------------
@flax.struct.dataclass
class ExecState:
    """Per-environment option execution (leading axis B)."""

    option: jax.Array      # int32, NO_OPTION when none runs
    subgoal: jax.Array     # (2,) the goal the running option pursues
    opt_steps: jax.Array   # int32 steps since the option started
    start_xy: jax.Array    # (2,) where the option started
    start_obs: jax.Array   # (obs_dim,) observation where the option started (DP inputs)
    traj: jax.Array        # (buffer_len, 2) last positions, oldest first
    traj_count: jax.Array  # int32 number of valid rows at the end of `traj`
    seg_id: jax.Array      # int32, increments at every option start (HER segments)


def exec_init(config: Config, obs, goal) -> ExecState:
    """No option running in any of the B environments (obs: (B, obs_dim))."""
    B = obs.shape[0]
    return ExecState(
        option=jnp.full((B,), NO_OPTION, jnp.int32),
        subgoal=jnp.broadcast_to(jnp.asarray(goal, jnp.float32), (B, 2)),
        opt_steps=jnp.zeros((B,), jnp.int32),
        start_xy=obs[:, :2],
        start_obs=obs,
        traj=jnp.zeros((B, config.chain.buffer_len, 2), jnp.float32),
        traj_count=jnp.zeros((B,), jnp.int32),
        seg_id=jnp.zeros((B,), jnp.int32),
    )


# ------------------------------------------------------------------------------------------------
# Seed groups: work that only some runs of a vmapped group need
# ------------------------------------------------------------------------------------------------
def any_seed(pred, seed_axis):
    """Scalar bool: `pred` holds in some run of the enclosing seed vmap (itself without one)."""
    if seed_axis is None:
        return pred
    return jax.lax.psum(pred.astype(jnp.int32), seed_axis) > 0


def all_seeds(pred, seed_axis):
    """Scalar bool: `pred` holds in every run of the enclosing seed vmap (itself without one)."""
    if seed_axis is None:
        return pred
    return ~any_seed(~pred, seed_axis)


# ------------------------------------------------------------------------------------------------
# Values and the model-based policy
# ------------------------------------------------------------------------------------------------
def value_fn(config: Config, td3, option=None):
    """value_fn(obs (..., obs_dim), goal (2,) or (..., 2)) -> (...): V(s | g) of the shared TD3, or
    with one TD3 per option (`config.per_option_td3`) of option `option`'s (a scalar, traced or
    not); a region policy's value ignores `goal` (its networks see the observation alone)."""
    tcfg = TD3Config.from_section(config.td3, config.model_based)
    if config.per_option_td3:
        if option is None:
            raise ValueError("per-option critics (shared_critic=False, dsc, dual): the value "
                             "function needs the option whose critic to use")
        td3 = td3_option(td3, jnp.asarray(option, jnp.int32))

    def fn(s, g):
        return td3_value(tcfg, td3, s, policy_goals(config, jnp.broadcast_to(g, s[..., :2].shape)))
    return fn


def policy_goals(config: Config, goals):
    """What the option policies take as their goal input: the goals (..., 2), or for region
    policies (`config.option_policies == "region"`) an empty (..., 0) array: they see the
    observation alone."""
    if config.option_policies == "region":
        return goals[..., :0]
    return goals


def value_net(config: Config, td3):
    """The shared TD3's actor and critic as MPC's fused terminal value (`mpc.td3_value_net`)."""
    return td3_value_net(TD3Config.from_section(config.td3, config.model_based), td3)


def mpc_actions(config: Config, dyn, key, obs, goals, value_fn, value_net=None):
    """(B, act): the first action of the cheapest of `config.mpc.samples` random sequences
    under eq. 2's cost (`mpc.mpc_actions`)."""
    mpc = MPCConfig.from_section(config.mpc, config.task.goal_tolerance, config.uses_value_in_mpc)
    return _mpc_shooting(mpc, DynamicsConfig.from_section(config.dynamics), dyn, key, obs, goals,
                         value_fn=value_fn, value_net=value_net)


# ------------------------------------------------------------------------------------------------
# Algorithm 2, one step: choose options and subgoals, act, end options, record outcomes
# ------------------------------------------------------------------------------------------------
def select_options(config: Config, chain, xy, prefer_pessimistic: bool = False):
    """(B,) the policy over options pi_O at positions xy (B, 2) (`options.select_option`)."""
    return jax.vmap(lambda p: select_option(chain, p, prefer_pessimistic=prefer_pessimistic))(xy)


def pick_subgoals(config: Config, chain, dp_table, td3, options, obs, keys):
    """(B, 2) subgoals g ~ beta_o for the options just chosen in B envs: robust sampling (the
    paper's Section 3.2) or the DP table's argmax (Algorithm 1's PICK-SUBGOAL)."""
    if config.option_policies == "region":
        # baseline DSC: an option pursues its whole target region, not a point; the subgoal is
        # only a placeholder shown in plots and videos: one robust sample of the target (a key
        # fixed per option and chain size)
        base = jax.random.PRNGKey(12345)
        keys = jax.vmap(lambda o: jax.random.fold_in(jax.random.fold_in(base, o),
                                                     chain.num_options))(options)
        return jax.vmap(lambda k, o: subgoals.robust_subgoal(k, chain, o))(keys, options)
    if config.subgoal == "dp":   # scored with the critic of the option that will pursue them
        return jax.vmap(lambda o, s: subgoals.pick_subgoal(
            dp_table, chain, o, s, value_fn(config, td3, o)))(options, obs)
    return jax.vmap(lambda k, o: subgoals.robust_subgoal(k, chain, o))(keys, options)


def choose_options(config: Config, env, chain, dp_table, td3, ex: ExecState, obs, key,
                   active=None, evaluation: bool = False) -> ExecState:
    """Start an option (and pick its subgoal) in every env whose `ex.option` is NO_OPTION
    (Algorithm 2, lines 4-5); flat algorithms run the global option towards the task goal.
    `active` (B,): only those envs start one. `evaluation`: the policy over options prefers
    pessimistic regions when `config.eval.prefer_pessimistic` is set."""
    B = obs.shape[0]
    xy = obs[:, :2]
    goal = jnp.asarray(env.goal, jnp.float32)
    need = ex.option == NO_OPTION
    if active is not None:
        need = need & active
    if config.hierarchical:
        keys = jax.random.split(key, B)
        pessimistic_first = evaluation and config.eval.prefer_pessimistic
        new_opt = select_options(config, chain, xy, pessimistic_first)              # (B,)
        sub = pick_subgoals(config, chain, dp_table, td3, new_opt, obs, keys)     # (B, 2)
    else:
        new_opt = jnp.full((B,), GLOBAL_OPTION, jnp.int32)
        sub = jnp.broadcast_to(goal, (B, 2))
    return ex.replace(
        option=jnp.where(need, new_opt, ex.option),
        subgoal=jnp.where(need[:, None], sub, ex.subgoal),
        opt_steps=jnp.where(need, 0, ex.opt_steps),
        start_xy=jnp.where(need[:, None], xy, ex.start_xy),
        start_obs=jnp.where(need[:, None], obs, ex.start_obs),
        traj_count=jnp.where(need, 0, ex.traj_count),
        seg_id=ex.seg_id + need.astype(jnp.int32),
    )


def policy_actions(config: Config, td3, dyn, obs, goals, key, explore: bool, rand_prob,
                   options=None):
    """(B, obs), (B, 2) -> (B, act): the option policy pi_o(. | g) (Algorithm 2, line 6): MPC
    over the learned model (eq. 2) or the actor; with exploration when `explore`.
    `options` (B,): the option each env runs; with one TD3 per option (`config.per_option_td3`)
    each env acts with its option's actor (NO_OPTION, an env that runs none, with the global
    option's). `rand_prob`: a scalar or one probability per env (B,)."""
    B = obs.shape[0]
    tcfg = TD3Config.from_section(config.td3, config.model_based)
    if config.per_option_td3:
        if config.model_based or options is None:
            raise ValueError("per-option actors (shared_critic=False, dsc, dual) act for "
                             "model-free algorithms and need the option of every env")
        params = td3_option(td3, jnp.clip(options, 0)).actor_params     # gathered per env
        acts = jax.vmap(lambda p, s, g: td3_act(tcfg, p, s, g))(params, obs,
                                                                policy_goals(config, goals))
        return td3_perturb(tcfg, acts, key, random_prob=rand_prob) if explore else acts
    if config.model_based:
        vf = vn = None
        if config.uses_value_in_mpc:
            vf = value_fn(config, td3)      # XLA paths
            vn = value_net(config, td3)     # fused into the MPC kernel on a GPU
        k_mpc, k_r, k_u = jax.random.split(key, 3)
        acts = mpc_actions(config, dyn, k_mpc, obs, goals, vf, vn)
        if explore:
            p = config.effective_random_prob
            rand = jax.random.uniform(k_u, acts.shape, acts.dtype, -1.0, 1.0)
            use = jax.random.uniform(k_r, (B,)) < p
            acts = jnp.where(use[:, None], rand, acts)
        return acts
    if explore:
        return td3_explore(tcfg, td3.actor_params, key, obs, goals, random_prob=rand_prob)
    return td3_act(tcfg, td3.actor_params, obs, goals)


def random_action_probs(config: Config, chain, options, run_successes) -> jax.Array:
    """The random-action probability of each env (B,) or of all of them (scalar).

    Per option (`config.exploration_per_option`, dsc and dual): `mf_initial_random_prob` while
    the executing option's own successes (``chain.successes``; the global option's are its own
    task-goal hits) are at most `mf_random_decay_successes`, else the effective
    `random_action_prob`, as the authors' ``MFOptionClass.py`` ``_get_epsilon`` (0.8 while
    ``num_goal_hits <= 3``, else 0.2; each option has its own counter). Otherwise the run-wide
    schedule of `td3.td3_random_prob` on `run_successes`."""
    if config.exploration_per_option:
        own = chain.successes[jnp.clip(options, 0)]
        return jnp.where(own <= config.td3.mf_random_decay_successes,
                         config.td3.mf_initial_random_prob, config.effective_random_prob).astype(jnp.float32)
    return td3_random_prob(TD3Config.from_section(config.td3, config.model_based), run_successes)


def push_traj(ex: ExecState, xy) -> ExecState:
    """Append the positions xy (B, 2) after a step to the running options' trajectories (the
    last `buffer_len` kept) and count the step."""
    traj = jnp.concatenate([ex.traj[:, 1:], xy[:, None, :]], axis=1)
    return ex.replace(traj=traj, traj_count=jnp.minimum(ex.traj_count + 1, ex.traj.shape[1]),
                      opt_steps=ex.opt_steps + 1)


def options_terminate(config: Config, chain, options, xy, goal):
    """(B,) bool: each env's option terminates at xy (B, 2), inside beta_o
    (`options.option_terminates`)."""
    o = jnp.clip(options, 0)
    return jax.vmap(lambda oo, p: option_terminates(chain, oo, p, goal))(o, xy)


def option_end(config: Config, env, chain, ex: ExecState, next_xy, done):
    """Local success / timeout / episode end of the running options (Algorithm 2, line 7: the
    option succeeds inside its termination region within tolerance of its subgoal; a region
    policy, `config.option_policies == "region"`, anywhere in its termination region, as the
    authors' ``MFOptionClass.py`` ``rollout``: ``is_term_true``). The global option times out
    after `config.effective_global_option_timeout` steps, the others after `option_timeout`.
    Call after `push_traj`. Returns (ended, success), (B,) bool each."""
    running = ex.option != NO_OPTION
    near = jnp.linalg.norm(next_xy - ex.subgoal, axis=-1) <= config.task.goal_tolerance
    if config.hierarchical:
        goal = jnp.asarray(env.goal, jnp.float32)
        term = options_terminate(config, chain, ex.option, next_xy, goal)
        success = running & term if config.option_policies == "region" else running & term & near
        # `ex.opt_steps` counts the steps already taken (the caller has pushed this step)
        timeout = ex.opt_steps >= config.chain.option_timeout
        if config.effective_global_option_timeout != config.chain.option_timeout:
            timeout = jnp.where(ex.option == GLOBAL_OPTION,
                                ex.opt_steps >= config.effective_global_option_timeout, timeout)
    else:
        success = running & near
        timeout = jnp.zeros_like(running)
    ended = running & (success | timeout | (done > 0))
    return ended, success


def record_outcomes(config: Config, chain, ex: ExecState, success, events):
    """The chain with the outcomes of the executions that ended (`events` (B,)) recorded
    (Algorithm 2, lines 8-11): a success adds the start and the trajectory as positive examples,
    a failure the start as a negative one (`options.record_outcomes`)."""
    T_ = ex.traj.shape[1]
    tmask = jnp.arange(T_)[None, :] >= (T_ - ex.traj_count)[:, None]
    return _record_outcomes(chain, jnp.clip(ex.option, 0), success, ex.start_xy, ex.traj, tmask,
                            events, start_obs=ex.start_obs)


def chain_metrics(config: Config, chain, start_xy=None) -> Dict[str, jax.Array]:
    """`options/*` scalars of the chain (`options.chain_metrics`; the chain probability is
    eq. 3)."""
    m = _chain_metrics(chain, None if start_xy is None else jnp.asarray(start_xy, jnp.float32))
    return {f"options/{k}": jnp.asarray(v, jnp.float32) for k, v in m.items()}


def option_table(chain) -> Dict[str, jax.Array]:
    """`table/*`: the option table's (K,) columns (`options.table_columns`), which the host
    writes to the run's options.csv instead of metrics.csv."""
    return {TABLE_PREFIX + k: jnp.asarray(v, jnp.int32) for k, v in table_columns(chain).items()}


# ------------------------------------------------------------------------------------------------
# Where training episodes start
# ------------------------------------------------------------------------------------------------
def frontier_candidates(config: Config, env, key):
    """(M, 2) candidate states for the frontier probe: the env's diverse-start sampler."""
    return jax.vmap(env.sample_start)(jax.random.split(key, config.frontier.candidates))


def frontier_pool(config: Config, env, chain, key):
    """(candidates (M, 2), pool (M,) bool): where this iteration's frontier starts come from
    (with `frontier.goal_starts`, also next to the task goal while the goal option is in
    gestation, `frontier.goal_pool`)."""
    cand = frontier_candidates(config, env, key)
    f = config.frontier
    pool = frontier.start_pool(chain, frontier.frontier_probe(chain, cand, f.radius,
                                                              f.inner_radius))
    if f.goal_starts:
        pool = pool | frontier.goal_pool(chain, cand, f.radius, f.inner_radius)
    return cand, pool


def diverse_starts(config: Config, env, k_start, B: int, front=None):
    """(B, 2) start positions of episodes that begin at a diverse start: the env's sampler, or,
    for a `frontier_start_prob` share of the envs (drawn with the same uniform that
    `task_start_prob` uses: [task start | frontier | diverse]), a random candidate of the frontier
    pool `front` = (candidates (M, 2), pool (M,) bool) when the pool holds any."""
    starts = jax.vmap(env.sample_start)(jax.random.split(k_start, B))
    if front is None:
        return starts
    u = jax.random.uniform(jax.random.fold_in(k_start, 1), (B,))
    at_front = ((u >= config.task.start_prob)
                & (u < config.task.start_prob + config.frontier.start_prob))
    cand, pool = front
    pick = jax.random.uniform(jax.random.fold_in(k_start, 2), (B,) + pool.shape)
    pick = jnp.argmax(jnp.where(pool[None, :], pick, -1.0), axis=1)
    return jnp.where((at_front & pool.any())[:, None], cand[pick], starts)


# ------------------------------------------------------------------------------------------------
# In-band evaluation: evaluation episodes stepped inside training's scan
# ------------------------------------------------------------------------------------------------
@flax.struct.dataclass
class InbandState:
    """In-band evaluation (`Config.eval.inband_envs` = E > 0): E envs that run evaluation episodes
    from the task start inside `train_step`, and the outcomes of the last K finished ones
    (K = `Config.inband_window`, a ring written in order of finishing)."""

    env_state: PyTree      # (E,) envs
    exec: ExecState        # (E,) their option execution
    key: jax.Array         # the stream's key: (k_reset, k_run) = split(key), as `evaluate` splits
    t: jax.Array           # int32 in-band steps taken; step t acts with fold_in(k_run, t)
    ep_steps: jax.Array    # (E,) int32 steps of the running episodes
    success: jax.Array     # (K,) bool: finished episode reached the goal
    steps: jax.Array       # (K,) int32: its length in steps
    episodes: jax.Array    # int32 in-band episodes finished so far (ring slot: episodes % K)


def where_rows(pred, on_true, on_false):
    """Per-row select over pytrees with a leading axis (pred: (E,))."""
    return jax.tree_util.tree_map(
        lambda a, b: jnp.where(pred.reshape(pred.shape + (1,) * (a.ndim - 1)), a, b),
        on_true, on_false)


def inband_act(config: Config, env, chain, dp_table, td3, dyn, ib: InbandState):
    """The evaluation policy at in-band step ``ib.t``: `evaluate.evaluate_episodes`' choice at its
    step t (option selection preferring pessimistic regions as configured, subgoals, MPC or the
    actor without exploration). Returns (exec state, (E, act) actions)."""
    _, k_run = jax.random.split(ib.key)
    k_opt, k_act = jax.random.split(jax.random.fold_in(k_run, ib.t))
    obs = ib.env_state.obs
    ex = choose_options(config, env, chain, dp_table, td3, ib.exec, obs, k_opt, evaluation=True)
    acts = policy_actions(config, td3, dyn, obs, ex.subgoal, k_act, False, 0.0, ex.option)
    return ex, acts


def inband_record(config: Config, env, chain, ib: InbandState, ex: ExecState, nes,
                  seed_axis=None) -> InbandState:
    """After the in-band envs stepped to `nes`: end their options as evaluation does, write the
    outcomes of finished episodes into the ring, restart those envs at the task start."""
    E, K = config.eval.inband_envs, config.inband_window
    ex = push_traj(ex, nes.obs[:, :2])
    done = nes.done > 0
    ended, _ = option_end(config, env, chain, ex, nes.obs[:, :2], nes.done)
    ex = ex.replace(option=jnp.where(ended, NO_OPTION, ex.option))
    ep_steps = ib.ep_steps + 1
    success = done & (nes.info["success"] > 0)
    # ring slots in order of finishing (env order within a step); when more than K finish in one
    # step only the last K are kept, so no two writes share a slot
    d = done.astype(jnp.int32)
    n_new = jnp.sum(d)
    rank = jnp.cumsum(d) - 1
    slot = jnp.where(done & (rank >= n_new - K), (ib.episodes + rank) % K, K)
    ring_success = ib.success.at[slot].set(success, mode="drop")
    ring_steps = ib.steps.at[slot].set(ep_steps, mode="drop")

    def restart(_):
        k_reset, _ = jax.random.split(ib.key)
        fresh = jax.vmap(env.reset)(jax.random.split(jax.random.fold_in(k_reset, ib.t + 1), E))
        return (select_states(done, fresh, nes),
                where_rows(done, exec_init(config, fresh.obs, env.goal), ex))

    es, ex = jax.lax.cond(any_seed(jnp.any(done), seed_axis), restart, lambda _: (nes, ex), None)
    return ib.replace(env_state=es, exec=ex, t=ib.t + 1, ep_steps=jnp.where(done, 0, ep_steps),
                      success=ring_success, steps=ring_steps, episodes=ib.episodes + n_new)


def inband_metrics(config: Config, ib: InbandState) -> Dict[str, jax.Array]:
    """Scalars over the last K finished in-band episodes (the window; fewer before K finished).

    inband/success_rate: share of the window that reached the goal (0 while none finished);
    inband/steps_to_goal: mean length of the window's successful episodes (`episode_length`
    while none succeeded); inband/episodes: finished so far; inband/window: episodes in the
    window. Never NaN: inband/window = 0 says that the first two mean nothing yet."""
    K = ib.success.shape[0]
    n = jnp.minimum(ib.episodes, K)
    valid = jnp.arange(K) < n        # slots fill from 0; all valid once K episodes finished
    succ = valid & ib.success
    n_succ = jnp.sum(succ.astype(jnp.int32))
    f = lambda x: jnp.asarray(x, jnp.float32)
    return {
        "inband/success_rate": f(jnp.where(n > 0, n_succ / jnp.maximum(n, 1), 0.0)),
        "inband/steps_to_goal": f(jnp.where(
            n_succ > 0, jnp.sum(jnp.where(succ, ib.steps, 0)) / jnp.maximum(n_succ, 1),
            config.task.episode_length)),
        "inband/episodes": f(ib.episodes),
        "inband/window": f(n),
    }
