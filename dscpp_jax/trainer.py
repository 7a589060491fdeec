"""The DSC++ training loop as pure functions: `init(key, config) -> TrainState` and the jitted
`train_step(state) -> (state, metrics)` (its docstring outlines the paper's Algorithms 2 and 3).

One `train_step` advances `num_envs` (B) environments `steps_per_iter` (T) steps inside a
`lax.scan` (`rollout`; environments vmapped), then learns (`learn`): TD3+HER gradient steps,
dynamics-model steps, classifier refits of the options that received new examples, chain growth
and the DP refresh. No host round trip happens inside; all sizes come from the static `Config`,
so the step compiles once. With B = 1 and T = one episode it follows the paper's sequential
schedule; with many environments it is the accelerated variant.

What one step of an environment does lives in `dscpp_jax.acting` (shared with evaluation), what
the learning phase does in `dscpp_jax.learning`; this module holds the state, the environments,
`init` and the wiring. Per environment step:
1. environments without a running option pick one (walk the chain from the goal option outward;
   the global option otherwise) and a subgoal for it (robust sampling or the DP table);
   flat algorithms always run the global option towards the task goal;
2. act: uniform random during warm-up; else MPC over the learned model (model based) or the
   actor with Gaussian noise and random actions (model free);
3. step; the option ends on local success (inside the termination region and within tolerance
   of the subgoal; the baselines' region policies: anywhere inside it), on its timeout (the
   global option's own, `Config.effective_global_option_timeout`), or when the episode ends
   (goal, time limit, NaN physics);
4. option outcomes are recorded in the chain (positives: start + last `buffer_len` positions;
   negatives: the start); transitions go to the HER replay (and the model replay);
5. finished episodes restart, from a diverse start once warm-up is over.

In-band evaluation (`Config.eval.inband_envs` = E > 0): E more environments run evaluation
episodes from the task start in the same scan, stepped in one physics batch of B + E with the
training environments (`envs.goal_env.join_states`; with `inband_eval_batched` off, by a second
vmapped step). They act with evaluation's deterministic policy (`acting.inband_act`), as of the
iteration's start, and write only `TrainState.inband` (their env and option state, and a ring of
the last finished outcomes); metrics `inband/*`.
"""
from __future__ import annotations

import functools
import os
import sys
import threading
from typing import Any, Dict, Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp

from dscpp_jax import envs
from dscpp_jax import acting, learning
# GLOBAL_OPTION and GOAL_OPTION are re-exported: part of trainer's API
from dscpp_jax.acting import (FRONTIER_KEY_SALT, GLOBAL_OPTION, GOAL_OPTION, NO_OPTION,  # noqa
                              ExecState, InbandState, all_seeds, any_seed, choose_options,
                              diverse_starts, exec_init, frontier_pool, inband_act,
                              inband_metrics, inband_record, option_end,
                              options_terminate, policy_actions, push_traj,
                              random_action_probs, record_outcomes)
from dscpp_jax.config import Config
from dscpp_jax.learning import td3_buffer, td3_sample_fn  # noqa: F401  (re-exported)
from dscpp_jax.options import ChainConfig, chain_init
from dscpp_jax.replay import RegionStep, Replay, TrajStep, replay_add, replay_init
from dscpp_jax.subgoals import dp_table_init
from dscpp_jax.td3 import TD3State, td3_init, td3_init_per_option, td3_random_prob
from dscpp_jax.envs.ant_maze import warp_available
from dscpp_jax.envs.goal_env import join_states, select_state, select_states, split_states
from dscpp_jax.envs.goals import goal_reached
from dscpp_jax.td3 import TD3Config

PyTree = Any


# ------------------------------------------------------------------------------------------------
# State
# ------------------------------------------------------------------------------------------------
@flax.struct.dataclass
class Counters:
    """Run counters (int32 scalars): environment steps, finished episodes, iterations, successful
    episodes and option executions."""

    env_steps: jax.Array
    episodes: jax.Array
    iteration: jax.Array
    episode_successes: jax.Array
    option_successes: jax.Array
    warmup_done: jax.Array   # bool: the model pretraining burst ran


@flax.struct.dataclass
class TrainState:
    """Everything a run carries from one `train_step` to the next (all of it checkpointed): the
    training envs and their running options, the skill chain, the learners, the replays, the DP
    table, the counters, the PRNG key and the static config."""

    env_state: PyTree
    exec: ExecState
    chain: PyTree
    td3: TD3State
    dyn: PyTree
    replay: Replay
    model_replay: PyTree
    dp_table: PyTree
    counters: Counters
    key: jax.Array
    config: Config = flax.struct.field(pytree_node=False)
    # None (no leaves, so checkpoints are those of a run without it) unless inband_eval_envs > 0
    inband: Optional[InbandState] = None


# ------------------------------------------------------------------------------------------------
# Environments and the learners' configs
# ------------------------------------------------------------------------------------------------
SEED_AXIS = "runs"
"""The vmap axis name over the runs of a seed group (see `train_step_impl`'s ``seed_axis``; the
device mesh's axis is `seed_group.SEED_AXIS`)."""


def resolve_physics(config: Config) -> Config:
    """`config` with ``physics="auto"`` made concrete: MuJoCo Warp on a GPU where `warp-lang` is
    installed, MJX-JAX elsewhere (point-mass envs: "jax", they have no MuJoCo physics)."""
    if config.task.physics != "auto":
        return config
    if config.env.startswith("point_"):
        return config.override(physics="jax")
    use_warp = jax.default_backend() == "gpu" and warp_available()
    return config.override(physics="warp" if use_warp else "jax")


def make_env(config: Config, worlds: Optional[int] = None):
    """The env of `config`. ``worlds``: the most envs stepped together (all vmapped axes
    multiplied out); it sizes MuJoCo Warp's shared contact buffers (default: the training batch,
    ``group_size * num_envs``)."""
    config = resolve_physics(config)
    if worlds is None:
        worlds = config.run.group_size * config.run.num_envs
    return _make_env(config.env, config.task.episode_length, config.task.goal_tolerance,
                     config.task.ant_integrator, config.task.physics, int(worlds))


@functools.lru_cache(maxsize=None)
def _make_env(name, episode_length, goal_tolerance, integrator, physics, worlds):
    # the first call may come from inside a trace (jit/vmap of init_impl): build the env's
    # constants eagerly so that none of them is a tracer that outlives it
    with jax.ensure_compile_time_eval():
        return _build_env(name, episode_length, goal_tolerance, integrator, physics, worlds)


def _build_env(name, episode_length, goal_tolerance, integrator, physics, worlds):
    kw = {} if name.startswith("point_") else dict(
        integrator=integrator, physics=physics,
        **({"warp_worlds": worlds} if physics == "warp" else {}))
    return envs.make(name, episode_length=episode_length, goal_tolerance=goal_tolerance, **kw)


def inband_batched(config: Config) -> bool:
    """Whether the in-band envs step in one batch with the training envs (one physics call over
    B + E worlds, `envs.goal_env.join_states`): `Config.eval.inband_batched`. Otherwise they take
    a second physics call of their own each step."""
    return config.eval.inband_batched


def inband_env(config: Config):
    """The env that resets the in-band envs (on MuJoCo Warp one whose shared contact buffers are
    sized for ``group_size * inband_eval_envs`` worlds, so that the in-band batch keeps its own)."""
    return make_env(config, worlds=config.run.group_size * config.eval.inband_envs)


def joint_env(config: Config):
    """The env that steps training and in-band envs together (`inband_batched`): sized for
    ``group_size * (num_envs + inband_eval_envs)`` worlds."""
    return make_env(config, worlds=config.run.group_size
                    * (config.run.num_envs + config.eval.inband_envs))


def step_env(config: Config):
    """The env whose physics step `train_step` runs (sized for every world it steps at once)."""
    if config.eval.inband_envs > 0 and inband_batched(config):
        return joint_env(config)
    return make_env(config)


WARP_BUILD_WORKERS_ENV = "DSCPP_JAX_WARP_BUILD_WORKERS"


def warp_build_workers() -> int:
    """How many MuJoCo Warp modules `prewarm_physics` compiles at once: $DSCPP_JAX_WARP_BUILD_WORKERS
    (1: one after another, as Warp alone would) or 0, one per CPU core up to 16
    (`envs.warp_kernels.default_workers`)."""
    text = os.environ.get(WARP_BUILD_WORKERS_ENV, "").strip()
    if not text:
        return 0
    try:
        n = int(text)
    except ValueError:
        n = -1
    if n < 0:
        raise ValueError(f"${WARP_BUILD_WORKERS_ENV}={text!r}: give a whole number of threads "
                         f"(0: one per CPU core up to 16; 1: one module after another)")
    return n


def prewarm_physics(config: Config) -> Optional[threading.Thread]:
    """On MuJoCo Warp with a GPU, start building Warp's kernels for `config`'s env in a thread
    (`AntMazeEnv.build_warp_kernels`, outside JAX) and return it; None elsewhere. Warp compiles a
    kernel at its first launch, which otherwise comes only once XLA has compiled the program that
    launches it; this lets the two compilers work at once. While the thread runs nothing else may
    launch MuJoCo Warp (launches from two threads at once crash, and `init` steps the env through
    it): compile ahead of time meanwhile (`compile_ahead`, or ``train_step.lower(state).compile()``
    once the state exists) and join the thread before `init` or a step runs. Every env the run
    uses is built before the thread starts. A failure here is left for the real step to report."""
    config = resolve_physics(config)
    workers = warp_build_workers()   # a bad setting is an error wherever it is read
    if config.task.physics != "warp" or config.env.startswith("point_") or jax.default_backend() != "gpu":
        return None
    # built here, before the thread: the env cache is no lock, and building an env allocates
    # MuJoCo Warp data
    make_env(config)
    if config.eval.inband_envs > 0:
        inband_env(config)
    env = step_env(config)

    def work():
        try:
            env.build_warp_kernels(workers=workers)
        except Exception as e:  # noqa: BLE001 - only a head start: the first step builds them
            print(f"warning: MuJoCo Warp's kernel build ahead of the first step failed "
                  f"({type(e).__name__}: {e}); they build at the first step", file=sys.stderr)

    thread = threading.Thread(target=work, name="warp-kernel-build", daemon=True)
    thread.start()
    return thread


INBAND_KEY_SALT = 0x1B_E7A1
"""`init`'s key folded with this gives the in-band stream's key (the training stream's keys come
from splitting `init`'s key, so they are the same with in-band evaluation on or off)."""
def observation_size(config: Config) -> int:
    """The observation size of `config`'s env."""
    return int(make_env(config).observation_size)


def action_size(config: Config) -> int:
    """The action size of `config`'s env."""
    return int(make_env(config).action_size)


# ------------------------------------------------------------------------------------------------
# init
# ------------------------------------------------------------------------------------------------
def init(key: jax.Array, config: Config) -> TrainState:
    """A fresh TrainState for `config` (validated first, before anything compiles); jitted, and
    vmap-able over `key`.

    The state carries `config.device_view()`: host-only fields (seed, schedule length, logging
    cadence) are reset there so that changing them never recompiles `train_step`."""
    if not isinstance(config, Config):
        raise TypeError(f"init(key, config) needs a dscpp_jax.Config as its second argument (e.g. "
                        f"dscpp_jax.preset('fast', env='point_u_maze')), got "
                        f"{type(config).__name__}")
    if not hasattr(key, "dtype"):
        raise TypeError(f"init(key, config) needs a PRNG key as its first argument (e.g. "
                        f"jax.random.PRNGKey(0)), got {type(key).__name__}")
    config = resolve_physics(config.validate()).device_view()
    make_env(config)  # unknown env names fail here, not inside a trace
    return init_jit(key, config)


def compile_ahead(key: jax.Array, config: Config, state: Optional[TrainState] = None) -> None:
    """XLA-compile `init(key, config)` and `train_step` on the shapes of its state, running
    neither (nothing steps the physics, so MuJoCo Warp's kernels can build meanwhile in
    `prewarm_physics`'s thread); the real calls then find their programs compiled. With `state`,
    only `train_step`, on `state` (a run that starts from a given state)."""
    if state is None:
        config = resolve_physics(config.validate()).device_view()
        init_jit.lower(key, config).compile()
        state = jax.eval_shape(init_jit, key, config)
    train_step.lower(state).compile()


def init_impl(key: jax.Array, config: Config) -> TrainState:
    """Un-jitted `init` (for use inside other traced code)."""
    config = resolve_physics(config).device_view()
    env = make_env(config)
    B, od, ad = config.run.num_envs, env.observation_size, env.action_size
    k_env, k_td3, k_dyn, k_run = jax.random.split(key, 4)
    env_state = jax.vmap(env.reset)(jax.random.split(k_env, B))
    goal = jnp.asarray(env.goal, jnp.float32)
    ex = exec_init(config, env_state.obs, env.goal)
    region = config.option_policies == "region"
    if not config.per_option_td3:
        td3 = td3_init(k_td3, od, 2, ad, TD3Config.from_section(config.td3, config.model_based))
    else:   # one TD3 per option slot: every leaf gets a leading (max_options,) axis; region
        # policies see the observation alone (no goal input)
        td3 = td3_init_per_option(k_td3, config.chain.max_options, od, 0 if region else 2, ad,
                                  TD3Config.from_section(config.td3, config.model_based))
    example = dict(obs=jnp.zeros((od,), jnp.float32), action=jnp.zeros((ad,), jnp.float32),
                   next_obs=jnp.zeros((od,), jnp.float32), goal=jnp.zeros((2,), jnp.float32),
                   seg_id=jnp.zeros((), jnp.int32),
                   option=jnp.zeros((), jnp.int32) if config.per_option_td3 else None)
    example = (RegionStep(**example, in_target=jnp.zeros((), bool), at_goal=jnp.zeros((), bool))
               if region else TrajStep(**example))
    replay = replay_init(example, config.td3.replay_capacity, B)
    if config.model_based:
        dyn = learning.init_dynamics(k_dyn, od, ad, config)
        model_replay = replay_init((jnp.zeros((od,)), jnp.zeros((ad,)), jnp.zeros((od,))),
                                   config.dynamics.capacity, B)
    else:
        dyn, model_replay = None, None
    if config.hierarchical:
        chain = chain_init(ChainConfig.from_section(
            config.chain, variant=config.classifier_variant,
            initiation_period=config.effective_initiation_period,
            goal_tolerance=config.task.goal_tolerance, obs_dim=observation_size(config)), goal)
    else:
        chain = None
    dp_table = dp_table_init(chain) if (config.hierarchical and config.subgoal == "dp") else None
    z = jnp.zeros((), jnp.int32)
    counters = Counters(env_steps=z, episodes=z, iteration=z, episode_successes=z,
                        option_successes=z, warmup_done=jnp.zeros((), bool))
    inband = inband_init(jax.random.fold_in(key, INBAND_KEY_SALT), config) \
        if config.eval.inband_envs > 0 else None
    return TrainState(env_state=env_state, exec=ex, chain=chain, td3=td3, dyn=dyn, replay=replay,
                      model_replay=model_replay, dp_table=dp_table, counters=counters, key=k_run,
                      config=config, inband=inband)


def inband_init(key: jax.Array, config: Config) -> InbandState:
    """E in-band envs at the task start, reset exactly as `evaluate_episodes(state, key, E)`
    resets its episodes; nothing finished yet."""
    env = inband_env(config)
    E, K = config.eval.inband_envs, config.inband_window
    k_reset, _ = jax.random.split(key)
    es = jax.vmap(env.reset)(jax.random.split(k_reset, E))
    z = jnp.zeros((), jnp.int32)
    return InbandState(env_state=es, exec=exec_init(config, es.obs, env.goal), key=key, t=z,
                       ep_steps=jnp.zeros((E,), jnp.int32), success=jnp.zeros((K,), bool),
                       steps=jnp.zeros((K,), jnp.int32), episodes=z)


init_jit = jax.jit(init_impl, static_argnames=("config",))
"""Jitted `init_impl(key, config)` (`init` validates its arguments first, then calls this)."""


# ------------------------------------------------------------------------------------------------
# Algorithm 2: the rollout (acting in B environments for T steps)
# ------------------------------------------------------------------------------------------------
def rollout(state: TrainState, key, seed_axis=None) -> Tuple[TrainState, Dict[str, jax.Array]]:
    """Algorithm 2's ROLLOUT over `config.run.steps_per_iter` steps of the `num_envs` training envs
    (and the in-band evaluation envs), one `lax.scan`: choose options and subgoals, act, step,
    end options, record their outcomes in the chain, push transitions to the replays, restart
    finished episodes. Returns (state, ``train/*``, ``frontier/pool`` and ``inband/*`` metrics)."""
    config = state.config
    env = make_env(config)
    B = config.run.num_envs
    warmup = state.counters.episodes < config.task.warmup_episodes
    tcfg = TD3Config.from_section(config.td3, config.model_based)
    n_succ = state.counters.option_successes if config.hierarchical else state.counters.episode_successes
    rand_prob = td3_random_prob(tcfg, n_succ)
    region = config.option_policies == "region"
    goal_xy = jnp.asarray(env.goal, jnp.float32)
    td3, dyn, dp_table = state.td3, state.dyn, state.dp_table
    act_dim = env.action_size

    # the in-band envs act with the policy as of this iteration's start, as `evaluate(state)` does
    ib_env, ib_chain = (inband_env(config), state.chain) if state.inband is not None else (None, None)
    # frontier starts (beyond the paper, dscpp_jax.frontier): candidates next to the region that
    # the link in gestation targets, fixed for the iteration (the chain changes between them)
    front = None
    if config.hierarchical and config.frontier.start_prob > 0:
        front = frontier_pool(config, env, state.chain, jax.random.fold_in(key, FRONTIER_KEY_SALT))

    def body(carry, k):
        es, ex, chain, replay, model_replay, acc, ib = carry
        k_opt, k_act, k_rand, k_reset, k_start = jax.random.split(k, 5)
        obs = es.obs

        # CHOOSE OPTIONS AND SUBGOALS (Alg. 2, l. 4-5)
        ex = choose_options(config, env, chain, dp_table, td3, ex, obs, k_opt)

        # ACT (Alg. 2, l. 6): random during warm-up, else the option policy with exploration.
        # Under a seed vmap a batched predicate would run the policy (MPC) on every step of
        # every seed: branch on "all seeds warm up", select per seed inside
        rand_acts = jax.random.uniform(k_rand, (B, act_dim), jnp.float32, -1.0, 1.0)
        # the random-action probability: run-wide, or per env of its executing option's own
        # successes (`acting.random_action_probs`)
        rp = (random_action_probs(config, chain, ex.option, n_succ)
              if config.exploration_per_option else rand_prob)
        acts = jax.lax.cond(
            all_seeds(warmup, seed_axis), lambda: rand_acts,
            lambda: jnp.where(warmup, rand_acts, policy_actions(
                config, td3, dyn, obs, ex.subgoal, k_act, True, rp, ex.option)))

        # STEP THE ENVS (the in-band envs too, in one physics batch or a second call)
        if ib is None:
            nes = jax.vmap(env.step)(es, acts)
        else:
            ib_ex, ib_acts = inband_act(config, ib_env, ib_chain, dp_table, td3, dyn, ib)
            if inband_batched(config):   # one physics batch of B + E envs
                j_env = step_env(config)
                like = jax.eval_shape(jax.vmap(j_env.reset),
                                      jax.random.split(k_reset, B + config.eval.inband_envs))
                both = jax.vmap(j_env.step)(join_states(es, ib.env_state, like),
                                            jnp.concatenate([acts, ib_acts], axis=0))
                nes, ib_nes = split_states(both, es, ib.env_state)
            else:
                nes = jax.vmap(env.step)(es, acts)
                ib_nes = jax.vmap(ib_env.step)(ib.env_state, ib_acts)
            ib = inband_record(config, ib_env, ib_chain, ib, ib_ex, ib_nes, seed_axis)
        next_xy = nes.obs[:, :2]
        nan = nes.info["nan"] > 0
        overflow = jnp.any(nes.info["overflow"] > 0)
        on_back = env.upright(nes.obs) < 0

        # END OPTIONS (Alg. 2, l. 7) AND RECORD THEIR OUTCOMES (l. 8-11); not during warm-up:
        # random actions say nothing about options
        ex = push_traj(ex, next_xy)
        ended, success = option_end(config, env, chain, ex, next_xy, nes.done)
        if config.hierarchical:
            events = ended & ~warmup
            chain = record_outcomes(config, chain, ex, success, events)

        # PUSH TRANSITIONS (s, o, a, s', g) TO THE REPLAYS. Region policies also store what their
        # rewards need, judged with this iteration's classifiers (they are refit only after the
        # rollout; the authors judge at the end of each option's execution with the classifiers
        # of that moment): s' in the option's target region, s' at the task goal
        step = dict(obs=obs, action=acts, next_obs=nes.obs, goal=ex.subgoal, seg_id=ex.seg_id,
                    option=ex.option if config.per_option_td3 else None)
        if region:
            step = RegionStep(**step,
                              in_target=options_terminate(config, chain, ex.option, next_xy,
                                                          goal_xy),
                              at_goal=goal_reached(next_xy, goal_xy, config.task.goal_tolerance))
        else:
            step = TrajStep(**step)
        replay = replay_add(replay, step, ~nan)
        if config.model_based:
            model_replay = replay_add(model_replay, (obs, acts, nes.obs), ~nan)

        # COUNT
        done = nes.done > 0
        ep_success = nes.info["success"] > 0
        acc = dict(acc)
        acc["episodes"] = acc["episodes"] + jnp.sum(done)
        acc["episode_successes"] = acc["episode_successes"] + jnp.sum(done & ep_success)
        acc["option_events"] = acc["option_events"] + jnp.sum(ended)
        acc["option_successes"] = acc["option_successes"] + jnp.sum(ended & success)
        acc["nan_episodes"] = acc["nan_episodes"] + jnp.sum(nan)
        acc["overflow_steps"] = acc["overflow_steps"] + overflow.astype(jnp.int32)
        acc["ep_len_sum"] = acc["ep_len_sum"] + jnp.sum(jnp.where(done, nes.info["steps"], 0))
        acc["on_back_steps"] = acc["on_back_steps"] + jnp.sum(on_back)
        if config.exploration_per_option:
            acc["random_prob_sum"] = acc["random_prob_sum"] + jnp.mean(rp)
        ex = ex.replace(option=jnp.where(ended, NO_OPTION, ex.option))

        # RESTART FINISHED EPISODES (diverse starts after warm-up). Whether the warm-up is over
        # counts the episodes finished up to this step: the envs' first episodes all end on one
        # step, and the episodes they begin there are the first after the warm-up
        warm_next = state.counters.episodes + acc["episodes"] < config.task.warmup_episodes

        def reset_all(_):
            ks = jax.random.split(k_reset, B)
            if config.task.diverse_starts:
                starts = diverse_starts(config, env, k_start, B, front)
                fresh_div = jax.vmap(env.reset_at)(ks, starts)
                fresh_task = jax.vmap(env.reset)(ks)
                fresh = select_state(warm_next, fresh_task, fresh_div)
                if config.task.start_prob > 0:
                    at_task = (jax.random.uniform(jax.random.fold_in(k_start, 1), (B,))
                               < config.task.start_prob)
                    fresh = select_states(at_task, fresh_task, fresh)
            else:
                fresh = jax.vmap(env.reset)(ks)
            return select_states(done, fresh, nes)

        nes = jax.lax.cond(any_seed(jnp.any(done), seed_axis), reset_all, lambda _: nes, None)
        return (nes, ex, chain, replay, model_replay, acc, ib), None

    z = jnp.zeros((), jnp.int32)
    acc0 = dict(episodes=z, episode_successes=z, option_events=z, option_successes=z,
                nan_episodes=z, ep_len_sum=z, overflow_steps=z, on_back_steps=z)
    if config.exploration_per_option:
        acc0["random_prob_sum"] = jnp.zeros((), jnp.float32)
    carry = (state.env_state, state.exec, state.chain, state.replay, state.model_replay, acc0,
             state.inband)
    carry, _ = jax.lax.scan(body, carry, jax.random.split(key, config.run.steps_per_iter))
    es, ex, chain, replay, model_replay, acc, inband = carry

    # COUNTERS AND METRICS
    c = state.counters
    counters = c.replace(
        env_steps=c.env_steps + B * config.run.steps_per_iter,
        episodes=c.episodes + acc["episodes"],
        episode_successes=c.episode_successes + acc["episode_successes"],
        option_successes=c.option_successes + acc["option_successes"],
    )
    state = state.replace(env_state=es, exec=ex, chain=chain, replay=replay,
                          model_replay=model_replay, counters=counters, inband=inband)
    n_ep = jnp.maximum(acc["episodes"], 1)
    metrics = {
        "train/episodes_finished": acc["episodes"].astype(jnp.float32),
        "train/episode_success": jnp.where(acc["episodes"] > 0,
                                           acc["episode_successes"] / n_ep, jnp.nan),
        "train/episode_length": jnp.where(acc["episodes"] > 0, acc["ep_len_sum"] / n_ep, jnp.nan),
        "train/option_events": acc["option_events"].astype(jnp.float32),
        "train/option_success": jnp.where(acc["option_events"] > 0,
                                          acc["option_successes"] / jnp.maximum(acc["option_events"], 1),
                                          jnp.nan),
        "train/nan_physics_steps": acc["nan_episodes"].astype(jnp.float32),
        # share of the training envs' steps that ended with the body on its back (the ant;
        # 0 for point masses): the paper's ant lies there until its episode ends
        "train/on_back_share": acc["on_back_steps"].astype(jnp.float32) / (B * config.run.steps_per_iter),
        "train/physics_overflow_steps": acc["overflow_steps"].astype(jnp.float32),
        "train/warmup": warmup.astype(jnp.float32),
        # per-option exploration: the mean over this iteration's steps and envs
        "train/random_action_prob": (acc["random_prob_sum"] / config.run.steps_per_iter
                                     if config.exploration_per_option else rand_prob),
    }
    if front is not None:
        metrics["frontier/pool"] = jnp.sum(front[1]).astype(jnp.float32)
    if inband is not None:
        metrics.update(inband_metrics(config, inband))
    return state, metrics


# ------------------------------------------------------------------------------------------------
# Learning, and the whole iteration
# ------------------------------------------------------------------------------------------------
def learn(state: TrainState, key, seed_axis=None) -> Tuple[TrainState, Dict[str, jax.Array]]:
    """The learning half of an iteration (`learning.learn` on `state`'s env)."""
    return learning.learn(state, make_env(state.config), key, seed_axis)


def train_step_impl(state: TrainState, seed_axis: Optional[str] = None
                    ) -> Tuple[TrainState, Dict[str, jax.Array]]:
    """One iteration (un-jitted; use `train_step`, whose docstring outlines it).

    ``seed_axis``: when this runs under ``jax.vmap(..., axis_name=seed_axis)`` over independent
    runs (a seed group), name that axis. Work that only some runs need (MPC during warm-up, resets,
    the dynamics pre-training burst, classifier refits, delayed actor steps) then runs when any run
    needs it, instead of on every call as a vmapped ``lax.cond`` would. Results are the same."""
    _check_state(state)
    key, k_roll, k_learn = jax.random.split(state.key, 3)
    state = state.replace(key=key)
    state, m_roll = rollout(state, k_roll, seed_axis)
    state, m_learn = learn(state, k_learn, seed_axis)
    c = state.counters
    metrics = {**m_roll, **m_learn,
               "counters/env_steps": c.env_steps.astype(jnp.float32),
               "counters/episodes": c.episodes.astype(jnp.float32),
               "counters/iteration": c.iteration.astype(jnp.float32)}
    return state, metrics


def select_train_state(pred, on_true: TrainState, on_false: TrainState) -> TrainState:
    """`on_true` where the scalar `pred` holds, else `on_false`: env states (the training and the
    in-band ones) merge with `select_state` (MuJoCo Warp's Data merges itself), every other leaf
    with `jnp.where`."""
    def strip(s):
        return s.replace(env_state=None, inband=None if s.inband is None
                         else s.inband.replace(env_state=None))
    rest = jax.tree_util.tree_map(lambda a, b: jnp.where(pred, a, b), strip(on_true),
                                  strip(on_false))
    out = rest.replace(env_state=select_state(pred, on_true.env_state, on_false.env_state))
    if on_true.inband is not None:
        out = out.replace(inband=rest.inband.replace(env_state=select_state(
            pred, on_true.inband.env_state, on_false.inband.env_state)))
    return out


def _check_state(state) -> None:
    if not isinstance(state, TrainState):
        raise TypeError(f"train_step(state) needs the TrainState made by dscpp_jax.init (or "
                        f"returned by train_step), got {type(state).__name__}")


_train_step_jit = jax.jit(train_step_impl)


def train_step(state: TrainState) -> Tuple[TrainState, Dict[str, jax.Array]]:
    """One iteration of DSC++ (or of a flat learner), jitted: `rollout`, then `learn`.

    Algorithm outline (the paper's Algorithms 2 and 3, one function per line; B envs, T steps)::

        rollout                        # Alg. 2 ROLLOUT: T steps of B envs in one lax.scan
          acting.choose_options        #   l. 4     o = pi_O(s_t) where no option runs
          acting.pick_subgoals         #   l. 5     g ~ beta_o (robust sampling; DP: Alg. 1)
          acting.policy_actions        #   l. 6     a ~ pi_o(s | g): MPC (eq. 2) or TD3's actor
          env.step
          acting.push_traj             #   l. 6     the option's trajectory tau
          acting.option_end            #   l. 7     s reached g in beta_o; timeout; episode end
          acting.record_outcomes       #   l. 8-11  tau: positive or negative examples of o
          replay_add                   #   l. 14    (s, o, a, s', g) into the HER replay
        learn                          # after the scan
          learning.update_policies     #   l. 14    TD3 + HER updates of pi_o and V(s | g)
          learning.update_dynamics     #   f_xi for MPC (model-based algorithms)
          learning.refit               #   l. 13    refit the options that received examples
          learning.grow_chain          # Alg. 3 l. 7-9  a new option while no I_o holds s_0
          learning.dp_value_table      # Alg. 1 CREATE-VALUE-TABLE (DP subgoals)

    The paper refits and updates after each option execution; here they run once per iteration,
    after B * T steps. Compiles once per Config; a TypeError for anything but a TrainState,
    before JAX tries to trace it."""
    _check_state(state)
    return _train_step_jit(state)


for _name in ("lower", "trace", "eval_shape", "_cache_size", "clear_cache"):
    if hasattr(_train_step_jit, _name):
        setattr(train_step, _name, getattr(_train_step_jit, _name))


def train_step_group_impl(states: TrainState) -> Tuple[TrainState, Dict[str, jax.Array]]:
    """`train_step_impl` over a leading seed axis (un-jitted): each run as if alone."""
    return jax.vmap(functools.partial(train_step_impl, seed_axis=SEED_AXIS),
                    axis_name=SEED_AXIS)(states)

