"""The DSC++ training loop as pure functions: `init(key, config) -> TrainState` and the jitted
`train_step(state) -> (state, metrics)`.

One `train_step` advances `num_envs` (B) environments `steps_per_iter` (T) steps inside a
`lax.scan` (environments vmapped), then learns: TD3+HER gradient steps, dynamics-model steps,
classifier refits of the options that received new examples, chain growth and the DP refresh.
No host round trip happens inside; all sizes come from the static `Config`, so the step compiles
once. With B = 1 and T = one episode it follows the paper's sequential schedule; with many
environments it is the accelerated variant.

Per environment step:
1. environments without a running option pick one (walk the chain from the goal option outward;
   the global option otherwise) and a subgoal for it (robust sampling or the DP table);
   flat algorithms always run the global option towards the task goal;
2. act: uniform random during warm-up; else MPC over the learned model (model based) or the
   actor with Gaussian noise and random actions (model free);
3. step; the option ends on local success (inside the termination region and within tolerance
   of the subgoal), on its timeout, or when the episode ends (goal, time limit, NaN physics);
4. option outcomes are recorded in the chain (positives: start + last `buffer_len` positions;
   negatives: the start); transitions go to the HER replay (and the model replay);
5. finished episodes restart, from a diverse start once warm-up is over.

In-band evaluation (`Config.inband_eval_envs` = E > 0): E more environments run evaluation
episodes from the task start in the same scan, stepped in one physics batch of B + E with the
training environments (`envs.goal_env.join_states`; with `inband_eval_batched` off, by a second
vmapped step). They act with `evaluate`'s
deterministic policy, as of the iteration's start, and write only `TrainState.inband` (their env
and option state, and a ring of the last finished outcomes); metrics `inband/*`.
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

from dscpp_jax.config import Config
from envs.goal_env import join_states, select_state, select_states, split_states
from dscpp_jax.replay import Replay, TrajStep, replay_add, replay_flatten, replay_init, replay_sample
from dscpp_jax.td3 import TD3Config, TD3State, td3_init, td3_explore, td3_act, td3_updates, td3_value, \
    td3_random_prob, td3_init_per_option, td3_option, td3_perturb, td3_updates_per_option

PyTree = Any
NO_OPTION = -1
GLOBAL_OPTION = 0
GOAL_OPTION = 1


# ------------------------------------------------------------------------------------------------
# State
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


@flax.struct.dataclass
class Counters:
    env_steps: jax.Array
    episodes: jax.Array
    iteration: jax.Array
    episode_successes: jax.Array
    option_successes: jax.Array
    warmup_done: jax.Array   # bool: the model pretraining burst ran


@flax.struct.dataclass
class InbandState:
    """In-band evaluation (`Config.inband_eval_envs` = E > 0): E envs that run evaluation episodes
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


@flax.struct.dataclass
class TrainState:
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
# Component configs derived from the run config
# ------------------------------------------------------------------------------------------------
SEED_AXIS = "runs"
"""The vmap axis name over the runs of a seed group (see `train_step_impl`'s ``seed_axis``; the
device mesh's axis is `seed_group.SEED_AXIS`)."""


def resolve_physics(config: Config) -> Config:
    """`config` with ``physics="auto"`` made concrete: MuJoCo Warp on a GPU where `warp-lang` is
    installed, MJX-JAX elsewhere (point-mass envs: "jax", they have no MuJoCo physics)."""
    if config.physics != "auto":
        return config
    if config.env.startswith("point_"):
        return config.override(physics="jax")
    from envs.ant_maze import warp_available
    use_warp = jax.default_backend() == "gpu" and warp_available()
    return config.override(physics="warp" if use_warp else "jax")


def make_env(config: Config, worlds: Optional[int] = None):
    """The env of `config`. ``worlds``: the most envs stepped together (all vmapped axes
    multiplied out); it sizes MuJoCo Warp's shared contact buffers (default: the training batch,
    ``group_size * num_envs``)."""
    config = resolve_physics(config)
    if worlds is None:
        worlds = config.group_size * config.num_envs
    return _make_env(config.env, config.episode_length, config.goal_tolerance,
                     config.ant_integrator, config.physics, int(worlds))


@functools.lru_cache(maxsize=None)
def _make_env(name, episode_length, goal_tolerance, integrator, physics, worlds):
    import envs
    # the first call may come from inside a trace (jit/vmap of init_impl): build the env's
    # constants eagerly so that none of them is a tracer that outlives it
    with jax.ensure_compile_time_eval():
        return _build_env(name, episode_length, goal_tolerance, integrator, physics, worlds)


def _build_env(name, episode_length, goal_tolerance, integrator, physics, worlds):
    import envs
    kw = {} if name.startswith("point_") else dict(
        integrator=integrator, physics=physics,
        **({"warp_worlds": worlds} if physics == "warp" else {}))
    return envs.make(name, episode_length=episode_length, goal_tolerance=goal_tolerance, **kw)


def inband_batched(config: Config) -> bool:
    """Whether the in-band envs step in one batch with the training envs (one physics call over
    B + E worlds, `envs.goal_env.join_states`): `Config.inband_eval_batched`. Otherwise they take
    a second physics call of their own each step."""
    return config.inband_eval_batched


def inband_env(config: Config):
    """The env that resets the in-band envs (on MuJoCo Warp one whose shared contact buffers are
    sized for ``group_size * inband_eval_envs`` worlds, so that the in-band batch keeps its own)."""
    return make_env(config, worlds=config.group_size * config.inband_eval_envs)


def joint_env(config: Config):
    """The env that steps training and in-band envs together (`inband_batched`): sized for
    ``group_size * (num_envs + inband_eval_envs)`` worlds."""
    return make_env(config, worlds=config.group_size * (config.num_envs + config.inband_eval_envs))


def step_env(config: Config):
    """The env whose physics step `train_step` runs (sized for every world it steps at once)."""
    if config.inband_eval_envs > 0 and inband_batched(config):
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
    if config.physics != "warp" or config.env.startswith("point_") or jax.default_backend() != "gpu":
        return None
    # built here, before the thread: the env cache is no lock, and building an env allocates
    # MuJoCo Warp data
    make_env(config)
    if config.inband_eval_envs > 0:
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
FRONTIER_KEY_SALT = 0xF0_27E1
"""The iteration's key folded with this gives the frontier candidates' key (dscpp_jax.frontier),
off the keys the rest of the iteration splits, so runs without the frontier are unchanged."""


def td3_config(config: Config) -> TD3Config:
    base = TD3Config.model_based if config.model_based else TD3Config.model_free
    kw = dict(batch_size=config.td3_batch_size, hidden=(config.td3_hidden, config.td3_hidden),
              discount=config.discount, exploration_noise=config.action_noise,
              replay_capacity=config.replay_capacity,
              actor_lr=config.effective_td3_lr, critic_lr=config.effective_td3_lr,
              action_l2=config.td3_action_l2, compute_dtype=config.td3_dtype)
    if config.td3_clip_targets:   # the value range under the 0 / -1 reward
        kw.update(target_range=(-1.0 / (1.0 - config.discount), 0.0))
    if config.random_action_prob >= 0:
        kw.update(random_action_prob=config.random_action_prob)
        if config.model_based:
            kw.update(random_action_prob_start=config.random_action_prob)
    if not config.model_based:
        kw.update(random_action_prob_start=config.mf_initial_random_prob,
                  random_action_switch_successes=config.mf_random_decay_successes)
    return base(**kw)


def _obs_dim(config: Config) -> int:
    return int(make_env(config).observation_size)


def _act_dim(config: Config) -> int:
    return int(make_env(config).action_size)


# ------------------------------------------------------------------------------------------------
# init
# ------------------------------------------------------------------------------------------------
def exec_init(config: Config, obs, goal) -> ExecState:
    """No option running in any of the B environments (obs: (B, obs_dim))."""
    B = obs.shape[0]
    return ExecState(
        option=jnp.full((B,), NO_OPTION, jnp.int32),
        subgoal=jnp.broadcast_to(jnp.asarray(goal, jnp.float32), (B, 2)),
        opt_steps=jnp.zeros((B,), jnp.int32),
        start_xy=obs[:, :2],
        start_obs=obs,
        traj=jnp.zeros((B, config.buffer_len, 2), jnp.float32),
        traj_count=jnp.zeros((B,), jnp.int32),
        seg_id=jnp.zeros((B,), jnp.int32),
    )


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
    return _init_jit(key, config)


def compile_ahead(key: jax.Array, config: Config, state: Optional[TrainState] = None) -> None:
    """XLA-compile `init(key, config)` and `train_step` on the shapes of its state, running
    neither (nothing steps the physics, so MuJoCo Warp's kernels can build meanwhile in
    `prewarm_physics`'s thread); the real calls then find their programs compiled. With `state`,
    only `train_step`, on `state` (a run that starts from a given state)."""
    if state is None:
        config = resolve_physics(config.validate()).device_view()
        _init_jit.lower(key, config).compile()
        state = jax.eval_shape(_init_jit, key, config)
    train_step.lower(state).compile()


def init_impl(key: jax.Array, config: Config) -> TrainState:
    """Un-jitted `init` (for use inside other traced code)."""
    config = resolve_physics(config).device_view()
    env = make_env(config)
    B, od, ad = config.num_envs, env.observation_size, env.action_size
    k_env, k_td3, k_dyn, k_run = jax.random.split(key, 4)
    env_state = jax.vmap(env.reset)(jax.random.split(k_env, B))
    goal = jnp.asarray(env.goal, jnp.float32)
    ex = exec_init(config, env_state.obs, env.goal)
    if config.shared_critic:
        td3 = td3_init(k_td3, od, 2, ad, td3_config(config))
    else:   # one TD3 per option slot: every leaf gets a leading (max_options,) axis
        td3 = td3_init_per_option(k_td3, config.max_options, od, 2, ad, td3_config(config))
    example = TrajStep(obs=jnp.zeros((od,), jnp.float32), action=jnp.zeros((ad,), jnp.float32),
                       next_obs=jnp.zeros((od,), jnp.float32), goal=jnp.zeros((2,), jnp.float32),
                       seg_id=jnp.zeros((), jnp.int32),
                       option=None if config.shared_critic else jnp.zeros((), jnp.int32))
    replay = replay_init(example, config.replay_capacity, B)
    if config.model_based:
        dyn = _dynamics_init(k_dyn, od, ad, config)
        model_replay = replay_init((jnp.zeros((od,)), jnp.zeros((ad,)), jnp.zeros((od,))),
                                   config.model_capacity, B)
    else:
        dyn, model_replay = None, None
    chain = _chain_init(config, goal) if config.hierarchical else None
    dp_table = _dp_table_init(config, chain) if (config.hierarchical and config.subgoal == "dp") \
        else None
    z = jnp.zeros((), jnp.int32)
    counters = Counters(env_steps=z, episodes=z, iteration=z, episode_successes=z,
                        option_successes=z, warmup_done=jnp.zeros((), bool))
    inband = inband_init(jax.random.fold_in(key, INBAND_KEY_SALT), config) \
        if config.inband_eval_envs > 0 else None
    return TrainState(env_state=env_state, exec=ex, chain=chain, td3=td3, dyn=dyn, replay=replay,
                      model_replay=model_replay, dp_table=dp_table, counters=counters, key=k_run,
                      config=config, inband=inband)


def inband_init(key: jax.Array, config: Config) -> InbandState:
    """E in-band envs at the task start, reset exactly as `evaluate_episodes(state, key, E)`
    resets its episodes; nothing finished yet."""
    env = inband_env(config)
    E, K = config.inband_eval_envs, config.inband_window
    k_reset, _ = jax.random.split(key)
    es = jax.vmap(env.reset)(jax.random.split(k_reset, E))
    z = jnp.zeros((), jnp.int32)
    return InbandState(env_state=es, exec=exec_init(config, es.obs, env.goal), key=key, t=z,
                       ep_steps=jnp.zeros((E,), jnp.int32), success=jnp.zeros((K,), bool),
                       steps=jnp.zeros((K,), jnp.int32), episodes=z)


_init_jit = jax.jit(init_impl, static_argnames=("config",))


# ------------------------------------------------------------------------------------------------
# Acting (shared by training and evaluation)
# ------------------------------------------------------------------------------------------------
def _choose_options(config: Config, env, chain, dp_table, td3, ex: ExecState, obs, key,
                    active=None, evaluation: bool = False):
    """Start an option (and pick its subgoal) in every env whose `ex.option` is NO_OPTION.
    `evaluation`: the policy over options prefers pessimistic regions when
    `config.eval_prefer_pessimistic` is set."""
    B = obs.shape[0]
    xy = obs[:, :2]
    goal = jnp.asarray(env.goal, jnp.float32)
    need = ex.option == NO_OPTION
    if active is not None:
        need = need & active
    if config.hierarchical:
        keys = jax.random.split(key, B)
        pessimistic_first = evaluation and config.eval_prefer_pessimistic
        new_opt = _select_option(config, chain, xy, pessimistic_first)        # (B,)
        sub = _pick_subgoals(config, chain, dp_table, td3, new_opt, obs, keys)  # (B, 2)
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


def _policy_actions(config: Config, td3, dyn, obs, goals, key, explore: bool, rand_prob,
                    options=None):
    """(B, obs), (B, 2) -> (B, act): MPC or the actor; with exploration when `explore`.
    `options` (B,): the option each env runs; with `config.shared_critic` off each env acts with
    its option's actor (NO_OPTION, an env that runs none, with the global option's)."""
    B = obs.shape[0]
    tcfg = td3_config(config)
    if not config.shared_critic:
        if config.model_based or options is None:
            raise ValueError("per-option actors (shared_critic=False) act for model-free "
                             "algorithms and need the option of every env")
        params = td3_option(td3, jnp.clip(options, 0)).actor_params     # gathered per env
        acts = jax.vmap(lambda p, s, g: td3_act(tcfg, p, s, g))(params, obs, goals)
        return td3_perturb(tcfg, acts, key, random_prob=rand_prob) if explore else acts
    if config.model_based:
        value_fn = value_net = None
        if config.uses_value_in_mpc:
            value_fn = _value_fn(config, td3)      # XLA paths
            value_net = _value_net(config, td3)    # fused into the MPC kernel on a GPU
        k_mpc, k_r, k_u = jax.random.split(key, 3)
        acts = _mpc_actions(config, dyn, k_mpc, obs, goals, value_fn, value_net)
        if explore:
            p = config.effective_random_prob
            rand = jax.random.uniform(k_u, acts.shape, acts.dtype, -1.0, 1.0)
            use = jax.random.uniform(k_r, (B,)) < p
            acts = jnp.where(use[:, None], rand, acts)
        return acts
    if explore:
        return td3_explore(tcfg, td3.actor_params, key, obs, goals, random_prob=rand_prob)
    return td3_act(tcfg, td3.actor_params, obs, goals)


def _option_end(config: Config, env, chain, ex: ExecState, next_xy, done):
    """Local success / timeout / episode end of the running options. Returns (ended, success)."""
    running = ex.option != NO_OPTION
    near = jnp.linalg.norm(next_xy - ex.subgoal, axis=-1) <= config.goal_tolerance
    if config.hierarchical:
        goal = jnp.asarray(env.goal, jnp.float32)
        term = _option_terminates(config, chain, ex.option, next_xy, goal)
        success = running & term & near
        # `ex.opt_steps` counts the steps already taken (the caller has pushed this step)
        timeout = ex.opt_steps >= config.option_timeout
    else:
        success = running & near
        timeout = jnp.zeros_like(running)
    ended = running & (success | timeout | (done > 0))
    return ended, success


def _push_traj(ex: ExecState, xy):
    traj = jnp.concatenate([ex.traj[:, 1:], xy[:, None, :]], axis=1)
    return ex.replace(traj=traj, traj_count=jnp.minimum(ex.traj_count + 1, ex.traj.shape[1]),
                      opt_steps=ex.opt_steps + 1)


# ------------------------------------------------------------------------------------------------
# train_step
# ------------------------------------------------------------------------------------------------
def _any_seed(pred, seed_axis):
    """Scalar bool: `pred` holds in some run of the enclosing seed vmap (itself without one)."""
    if seed_axis is None:
        return pred
    return jax.lax.psum(pred.astype(jnp.int32), seed_axis) > 0


def _all_seeds(pred, seed_axis):
    if seed_axis is None:
        return pred
    return ~_any_seed(~pred, seed_axis)


def _rollout(state: TrainState, key, seed_axis=None) -> Tuple[TrainState, Dict[str, jax.Array]]:
    config = state.config
    env = make_env(config)
    B = config.num_envs
    warmup = state.counters.episodes < config.warmup_episodes
    tcfg = td3_config(config)
    n_succ = state.counters.option_successes if config.hierarchical else state.counters.episode_successes
    rand_prob = td3_random_prob(tcfg, n_succ)
    td3, dyn, dp_table = state.td3, state.dyn, state.dp_table
    act_dim = env.action_size

    # the in-band envs act with the policy as of this iteration's start, as `evaluate(state)` does
    ib_env, ib_chain = (inband_env(config), state.chain) if state.inband is not None else (None, None)
    # frontier starts (beyond the paper, dscpp_jax.frontier): candidates next to the region that
    # the link in gestation targets, fixed for the iteration (the chain changes between them)
    front = None
    if config.hierarchical and config.frontier_start_prob > 0:
        front = _frontier_pool(config, env, state.chain,
                               jax.random.fold_in(key, FRONTIER_KEY_SALT))

    def body(carry, k):
        es, ex, chain, replay, model_replay, acc, ib = carry
        k_opt, k_act, k_rand, k_reset, k_start = jax.random.split(k, 5)
        obs = es.obs
        xy = obs[:, :2]
        ex = _choose_options(config, env, chain, dp_table, td3, ex, obs, k_opt)
        rand_acts = jax.random.uniform(k_rand, (B, act_dim), jnp.float32, -1.0, 1.0)
        # under a seed vmap a batched predicate would run the policy (MPC) on every step of
        # every seed: branch on "all seeds warm up", select per seed inside
        acts = jax.lax.cond(
            _all_seeds(warmup, seed_axis), lambda: rand_acts,
            lambda: jnp.where(warmup, rand_acts, _policy_actions(
                config, td3, dyn, obs, ex.subgoal, k_act, True, rand_prob, ex.option)))
        if ib is None:
            nes = jax.vmap(env.step)(es, acts)
        else:
            ib_ex, ib_acts = _inband_act(config, ib_env, ib_chain, dp_table, td3, dyn, ib)
            if inband_batched(config):   # one physics batch of B + E envs
                j_env = step_env(config)
                like = jax.eval_shape(jax.vmap(j_env.reset),
                                      jax.random.split(k_reset, B + config.inband_eval_envs))
                both = jax.vmap(j_env.step)(join_states(es, ib.env_state, like),
                                            jnp.concatenate([acts, ib_acts], axis=0))
                nes, ib_nes = split_states(both, es, ib.env_state)
            else:
                nes = jax.vmap(env.step)(es, acts)
                ib_nes = jax.vmap(ib_env.step)(ib.env_state, ib_acts)
            ib = _inband_record(config, ib_env, ib_chain, ib, ib_ex, ib_nes, seed_axis)
        next_xy = nes.obs[:, :2]
        nan = nes.info["nan"] > 0
        overflow = jnp.any(nes.info["overflow"] > 0)
        on_back = env.upright(nes.obs) < 0
        ex = _push_traj(ex, next_xy)
        ended, success = _option_end(config, env, chain, ex, next_xy, nes.done)
        # record option outcomes (not during warm-up: random actions say nothing about options)
        if config.hierarchical:
            events = ended & ~warmup
            chain = _record_outcomes(config, chain, ex, success, events)
        replay = replay_add(replay, TrajStep(
            obs=obs, action=acts, next_obs=nes.obs, goal=ex.subgoal, seg_id=ex.seg_id,
            option=None if config.shared_critic else ex.option), ~nan)
        if config.model_based:
            model_replay = replay_add(model_replay, (obs, acts, nes.obs), ~nan)
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
        ex = ex.replace(option=jnp.where(ended, NO_OPTION, ex.option))

        # auto-reset finished episodes (diverse starts after warm-up). Whether the warm-up is
        # over counts the episodes finished up to this step: the envs' first episodes all end
        # on one step, and the episodes they begin there are the first after the warm-up
        warm_next = state.counters.episodes + acc["episodes"] < config.warmup_episodes

        def reset_all(_):
            ks = jax.random.split(k_reset, B)
            if config.diverse_starts:
                starts = _diverse_starts(config, env, k_start, B, front)
                fresh_div = jax.vmap(env.reset_at)(ks, starts)
                fresh_task = jax.vmap(env.reset)(ks)
                fresh = select_state(warm_next, fresh_task, fresh_div)
                if config.task_start_prob > 0:
                    at_task = (jax.random.uniform(jax.random.fold_in(k_start, 1), (B,))
                               < config.task_start_prob)
                    fresh = select_states(at_task, fresh_task, fresh)
            else:
                fresh = jax.vmap(env.reset)(ks)
            return select_states(done, fresh, nes)

        nes = jax.lax.cond(_any_seed(jnp.any(done), seed_axis), reset_all, lambda _: nes, None)
        return (nes, ex, chain, replay, model_replay, acc, ib), None

    K = config.max_options
    z = jnp.zeros((), jnp.int32)
    acc0 = dict(episodes=z, episode_successes=z, option_events=z, option_successes=z,
                nan_episodes=z, ep_len_sum=z, overflow_steps=z, on_back_steps=z)
    carry = (state.env_state, state.exec, state.chain, state.replay, state.model_replay, acc0,
             state.inband)
    carry, _ = jax.lax.scan(body, carry, jax.random.split(key, config.steps_per_iter))
    es, ex, chain, replay, model_replay, acc, inband = carry
    c = state.counters
    counters = c.replace(
        env_steps=c.env_steps + B * config.steps_per_iter,
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
        "train/on_back_share": acc["on_back_steps"].astype(jnp.float32) / (B * config.steps_per_iter),
        "train/physics_overflow_steps": acc["overflow_steps"].astype(jnp.float32),
        "train/warmup": warmup.astype(jnp.float32),
        "train/random_action_prob": rand_prob,
    }
    if front is not None:
        metrics["frontier/pool"] = jnp.sum(front[1]).astype(jnp.float32)
    if inband is not None:
        metrics.update(inband_metrics(config, inband))
    return state, metrics


# ------------------------------------------------------------------------------------------------
# In-band evaluation
# ------------------------------------------------------------------------------------------------
def _where_rows(pred, on_true, on_false):
    """Per-row select over pytrees with a leading axis (pred: (E,))."""
    return jax.tree_util.tree_map(
        lambda a, b: jnp.where(pred.reshape(pred.shape + (1,) * (a.ndim - 1)), a, b),
        on_true, on_false)


def _inband_act(config: Config, env, chain, dp_table, td3, dyn, ib: InbandState):
    """The evaluation policy at in-band step ``ib.t``: `_eval_impl`'s choice at its step t (option
    selection preferring pessimistic regions as configured, subgoals, MPC or the actor without
    exploration). Returns (exec state, (E, act) actions)."""
    _, k_run = jax.random.split(ib.key)
    k_opt, k_act = jax.random.split(jax.random.fold_in(k_run, ib.t))
    obs = ib.env_state.obs
    ex = _choose_options(config, env, chain, dp_table, td3, ib.exec, obs, k_opt, evaluation=True)
    acts = _policy_actions(config, td3, dyn, obs, ex.subgoal, k_act, False, 0.0, ex.option)
    return ex, acts


def _inband_record(config: Config, env, chain, ib: InbandState, ex: ExecState, nes,
                   seed_axis=None) -> InbandState:
    """After the in-band envs stepped to `nes`: end their options as `_eval_impl` does, write the
    outcomes of finished episodes into the ring, restart those envs at the task start."""
    E, K = config.inband_eval_envs, config.inband_window
    ex = _push_traj(ex, nes.obs[:, :2])
    done = nes.done > 0
    ended, _ = _option_end(config, env, chain, ex, nes.obs[:, :2], nes.done)
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
                _where_rows(done, exec_init(config, fresh.obs, env.goal), ex))

    es, ex = jax.lax.cond(_any_seed(jnp.any(done), seed_axis), restart, lambda _: (nes, ex), None)
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
            config.episode_length)),
        "inband/episodes": f(ib.episodes),
        "inband/window": f(n),
    }


def _learn(state: TrainState, key, seed_axis=None) -> Tuple[TrainState, Dict[str, jax.Array]]:
    config = state.config
    env = make_env(config)
    tcfg = td3_config(config)
    k_td3, k_dyn, k_pre = jax.random.split(key, 3)
    metrics: Dict[str, jax.Array] = {}
    if config.shared_critic:
        td3, tm = td3_updates(tcfg, state.td3, td3_buffer(config, state.replay), k_td3,
                              config.td3_updates,
                              td3_sample_fn(config, env), sample_block=config.td3_sample_block,
                              seed_axis=seed_axis)
    else:
        # the shared TD3's steps, shared among the options in proportion to the replay entries
        # each collected; each learns on minibatches of its own transitions (HER within them)
        td3, tm = td3_updates_per_option(tcfg, state.td3, state.replay, state.replay.data.option,
                                         k_td3, config.td3_updates, td3_sample_fn(config, env),
                                         sample_block=config.td3_sample_block,
                                         seed_axis=seed_axis)
    metrics.update({f"td3/{k}": v for k, v in tm.items()})
    finite = {"td3": _all_finite(td3)}
    dyn = state.dyn
    counters = state.counters
    if config.model_based:
        warmup = counters.episodes < config.warmup_episodes
        dyn = _dynamics_fit_normaliser(config, dyn, state.model_replay)
        dyn, dm = _dynamics_updates(config, dyn, state.model_replay, k_dyn, config.dyn_updates)
        # one longer burst once the warm-up data is in (the original's 50 epochs)
        do_pre = (~warmup) & (~counters.warmup_done)
        if config.dyn_pretrain_steps > 0:
            def pretrain(d):
                new = _dynamics_updates(config, d, state.model_replay, k_pre,
                                        config.dyn_pretrain_steps)[0]
                return jax.tree_util.tree_map(lambda a, b: jnp.where(do_pre, a, b), new, d)
            dyn = jax.lax.cond(_any_seed(do_pre, seed_axis), pretrain, lambda d: d, dyn)
        counters = counters.replace(warmup_done=counters.warmup_done | do_pre)
        metrics.update({f"dynamics/{k}": v for k, v in dm.items()})
        finite["dynamics"] = _all_finite(dyn)
    chain, dp_table = state.chain, state.dp_table
    if config.hierarchical:
        chain = _refit(config, chain, seed_axis)
        if config.frontier_parent:
            from dscpp_jax import frontier
            from dscpp_jax.options import mature_options
            cand = _frontier_candidates(config, env, jax.random.fold_in(key, FRONTIER_KEY_SALT))
            chain = mature_options(chain)
            # growth leaves mature rows as they are, so this holds for the grown chain too
            is_open = frontier.open_rows(frontier.frontier_probe(chain, cand,
                                                                 config.frontier_radius),
                                         config.frontier_min_open)
            g0, p0 = frontier.gestation_row(chain), chain.parent
            chain = _grow_chain(config, chain, jnp.asarray(env.start, jnp.float32), is_open)
            g = frontier.gestation_row(chain)
            gc = jnp.clip(g, 0)
            metrics["frontier/retargeted"] = ((g >= 0) & (g == g0)
                                              & (chain.parent[gc] != p0[gc])).astype(jnp.float32)
            metrics["frontier/open_rows"] = jnp.sum(is_open).astype(jnp.float32)
        else:
            chain = _grow_chain(config, chain, jnp.asarray(env.start, jnp.float32))
        if config.subgoal == "dp":
            dp_table = _dp_value_table(config, chain, td3)
        metrics.update(_chain_metrics(config, chain, env.start))
        finite["classifiers"] = _all_finite(chain.clf)
    for k, v in finite.items():
        metrics[f"finite/{k}"] = v.astype(jnp.float32)
    counters = counters.replace(iteration=counters.iteration + 1)
    state = state.replace(td3=td3, dyn=dyn, chain=chain, dp_table=dp_table, counters=counters)
    return state, metrics


def _all_finite(tree) -> jax.Array:
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)
              if hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.ones((), bool)


def train_step_impl(state: TrainState, seed_axis: Optional[str] = None
                    ) -> Tuple[TrainState, Dict[str, jax.Array]]:
    """One iteration (un-jitted; use `train_step`).

    ``seed_axis``: when this runs under ``jax.vmap(..., axis_name=seed_axis)`` over independent
    runs (a seed group), name that axis. Work that only some runs need (MPC during warm-up, resets,
    the dynamics pre-training burst, classifier refits, delayed actor steps) then runs when any run
    needs it, instead of on every call as a vmapped ``lax.cond`` would. Results are the same."""
    _check_state(state)
    key, k_roll, k_learn = jax.random.split(state.key, 3)
    state = state.replace(key=key)
    state, m_roll = _rollout(state, k_roll, seed_axis)
    state, m_learn = _learn(state, k_learn, seed_axis)
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
    """One iteration, jitted (compiles once per Config); a TypeError for anything but a
    TrainState, before JAX tries to trace it."""
    _check_state(state)
    return _train_step_jit(state)


for _name in ("lower", "trace", "eval_shape", "_cache_size", "clear_cache"):
    if hasattr(_train_step_jit, _name):
        setattr(train_step, _name, getattr(_train_step_jit, _name))
"""Jitted `train_step(state) -> (state, metrics)`; compiles once per Config."""


def train_step_group_impl(states: TrainState) -> Tuple[TrainState, Dict[str, jax.Array]]:
    """`train_step_impl` over a leading seed axis (un-jitted): each run as if alone."""
    return jax.vmap(functools.partial(train_step_impl, seed_axis=SEED_AXIS),
                    axis_name=SEED_AXIS)(states)


# ------------------------------------------------------------------------------------------------
# Thin adapters over the component modules (one place to follow their signatures)
# ------------------------------------------------------------------------------------------------
def _her_max_segment(config: Config) -> int:
    return config.option_timeout if config.hierarchical else config.episode_length


def td3_buffer(config: Config, replay: Replay) -> Any:
    """The replay as TD3's minibatches are drawn from it in one learning phase: indexed once
    (``her.her_index``), so that each draw of ``td3_sample_fn`` is a few gathers."""
    from dscpp_jax.her import her_index
    return her_index(replay, _her_max_segment(config))


def td3_sample_fn(config: Config, env: Any = None) -> Any:
    """``sample_fn(key, replay, n) -> Transition`` for TD3: HER relabelling within an option's
    segment (the episode's for the flat algorithms). ``replay`` is a Replay or its
    :func:`td3_buffer` (the same draws, cheaper). ``env`` is unused (kept for callers)."""
    max_seg = _her_max_segment(config)

    def sample_fn(k, buf, n):
        return _her_sample(k, buf, n, strategy=config.her_strategy,
                           relabel_prob=config.her_relabel_prob, max_segment=max_seg,
                           goal_tolerance=config.goal_tolerance)

    return sample_fn


def _her_sample(key, buf, n, **kw):
    from dscpp_jax.her import her_sample
    return her_sample(key, buf, n, **kw)


def dyn_config(config: Config):
    from dscpp_jax.dynamics import DynamicsConfig
    return DynamicsConfig(ensemble_size=config.dyn_ensemble,
                          hidden=(config.dyn_hidden, config.dyn_hidden), lr=config.dyn_lr,
                          batch_size=config.dyn_batch_size)


def _dynamics_init(key, obs_dim, act_dim, config: Config):
    from dscpp_jax.dynamics import dynamics_init
    return dynamics_init(key, obs_dim, act_dim, dyn_config(config))


def _dynamics_fit_normaliser(config: Config, dyn, model_replay: Replay):
    from dscpp_jax.dynamics import dynamics_fit_normaliser
    obs, act, nxt = model_replay.data
    return dynamics_fit_normaliser(dyn, obs, act, nxt, model_replay.valid, cfg=dyn_config(config))


def _dynamics_updates(config: Config, dyn, model_replay: Replay, key, num_steps: int):
    from dscpp_jax.dynamics import dynamics_train
    obs, act, nxt = model_replay.data
    dyn, m = dynamics_train(dyn_config(config), dyn, (obs, act, nxt, model_replay.valid), key,
                            int(num_steps))
    return dyn, {"loss": jnp.mean(m["loss"]), "loss_last": m["loss"][-1]}


def mpc_config(config: Config):
    from dscpp_jax.mpc import MPCConfig
    return MPCConfig(num_samples=config.mpc_samples, horizon=config.mpc_horizon,
                     discount=config.mpc_discount, goal_tolerance=config.goal_tolerance,
                     use_value=config.uses_value_in_mpc, compute_dtype=config.mpc_dtype,
                     backend=config.mpc_backend)


def _mpc_actions(config: Config, dyn, key, obs, goals, value_fn, value_net=None):
    from dscpp_jax.mpc import mpc_actions
    return mpc_actions(mpc_config(config), dyn_config(config), dyn, key, obs, goals,
                       value_fn=value_fn, value_net=value_net)


def _value_net(config: Config, td3):
    from dscpp_jax.mpc import td3_value_net
    return td3_value_net(td3_config(config), td3)


def chain_config(config: Config):
    from dscpp_jax.options import ChainConfig
    return ChainConfig(max_options=config.max_options, gestation=config.gestation,
                       buffer_len=config.buffer_len, option_timeout=config.option_timeout,
                       max_pos_traj=config.max_pos_traj, max_neg=config.max_neg,
                       variant=config.classifier_variant, goal_tolerance=config.goal_tolerance,
                       subgoal_tolerance=config.goal_tolerance, obs_dim=_obs_dim(config),
                       svm_gamma=config.svm_gamma, svm_backend=config.svm_backend)


def _chain_init(config: Config, goal):
    from dscpp_jax.options import chain_init
    return chain_init(chain_config(config), goal)


def _dp_table_init(config: Config, chain):
    from dscpp_jax.subgoals import dp_table_init
    return dp_table_init(chain)


def _select_option(config: Config, chain, xy, prefer_pessimistic: bool = False):
    from dscpp_jax.options import select_option
    return jax.vmap(lambda p: select_option(chain, p, prefer_pessimistic=prefer_pessimistic))(xy)


def _value_fn(config: Config, td3, option=None):
    """value_fn(obs (..., obs_dim), goal (2,) or (..., 2)) -> (...): V(s | g) of the shared TD3, or
    with `config.shared_critic` off of option `option`'s (a scalar, traced or not)."""
    tcfg = td3_config(config)
    if not config.shared_critic:
        if option is None:
            raise ValueError("per-option critics (shared_critic=False): the value function needs "
                             "the option whose critic to use")
        td3 = td3_option(td3, jnp.asarray(option, jnp.int32))

    def value_fn(s, g):
        return td3_value(tcfg, td3, s, jnp.broadcast_to(g, s[..., :2].shape))
    return value_fn


def _pick_subgoals(config: Config, chain, dp_table, td3, options, obs, keys):
    """(B, 2) subgoals for the options just chosen in B envs."""
    from dscpp_jax import subgoals
    if config.algo in ("dsc", "dual"):
        # baseline DSC: each option pursues one target at a time (a key fixed per option and
        # chain size), not a goal re-sampled at every execution
        base = jax.random.PRNGKey(12345)
        keys = jax.vmap(lambda o: jax.random.fold_in(jax.random.fold_in(base, o),
                                                     chain.num_options))(options)
        return jax.vmap(lambda k, o: subgoals.robust_subgoal(k, chain, o))(keys, options)
    if config.subgoal == "dp":   # scored with the critic of the option that will pursue them
        return jax.vmap(lambda o, s: subgoals.pick_subgoal(
            dp_table, chain, o, s, _value_fn(config, td3, o)))(options, obs)
    return jax.vmap(lambda k, o: subgoals.robust_subgoal(k, chain, o))(keys, options)


def _option_terminates(config: Config, chain, options, xy, goal):
    from dscpp_jax.options import option_terminates
    o = jnp.clip(options, 0)
    return jax.vmap(lambda oo, p: option_terminates(chain, oo, p, goal))(o, xy)


def _record_outcomes(config: Config, chain, ex: ExecState, success, events):
    from dscpp_jax.options import record_outcomes
    T_ = ex.traj.shape[1]
    tmask = jnp.arange(T_)[None, :] >= (T_ - ex.traj_count)[:, None]
    return record_outcomes(chain, jnp.clip(ex.option, 0), success, ex.start_xy, ex.traj, tmask,
                           events, start_obs=ex.start_obs)


def _refit(config: Config, chain, seed_axis=None):
    from dscpp_jax.options import refit
    return refit(chain, seed_axis=seed_axis)


def _grow_chain(config: Config, chain, start_xy, is_open=None):
    from dscpp_jax.options import grow_chain
    return grow_chain(chain, start_xy, is_open)


def _diverse_starts(config: Config, env, k_start, B: int, front=None):
    """(B, 2) start positions of episodes that begin at a diverse start: the env's sampler, or,
    for a `frontier_start_prob` share of the envs (drawn with the same uniform that
    `task_start_prob` uses: [task start | frontier | diverse]), a random candidate of the frontier
    pool `front` = (candidates (M, 2), pool (M,) bool) when the pool holds any."""
    starts = jax.vmap(env.sample_start)(jax.random.split(k_start, B))
    if front is None:
        return starts
    u = jax.random.uniform(jax.random.fold_in(k_start, 1), (B,))
    at_front = ((u >= config.task_start_prob)
                & (u < config.task_start_prob + config.frontier_start_prob))
    cand, pool = front
    pick = jax.random.uniform(jax.random.fold_in(k_start, 2), (B,) + pool.shape)
    pick = jnp.argmax(jnp.where(pool[None, :], pick, -1.0), axis=1)
    return jnp.where((at_front & pool.any())[:, None], cand[pick], starts)


def _frontier_candidates(config: Config, env, key):
    """(M, 2) candidate states for the frontier probe: the env's diverse-start sampler."""
    return jax.vmap(env.sample_start)(jax.random.split(key, config.frontier_candidates))


def _frontier_pool(config: Config, env, chain, key):
    """(candidates (M, 2), pool (M,) bool): where this iteration's frontier starts come from."""
    from dscpp_jax import frontier
    cand = _frontier_candidates(config, env, key)
    return cand, frontier.start_pool(chain, frontier.frontier_probe(
        chain, cand, config.frontier_radius, config.frontier_inner_radius))


def _dp_value_table(config: Config, chain, td3):
    from dscpp_jax.subgoals import dp_value_table
    if config.shared_critic:
        return dp_value_table(chain, _value_fn(config, td3), gamma=config.mpc_discount)
    # each option's row of the table is valued with its own critic
    return dp_value_table(chain, None, gamma=config.mpc_discount,
                          option_value_fn=lambda k, s, g: _value_fn(config, td3, k)(s, g))


def _chain_metrics(config: Config, chain, start_xy=None):
    from dscpp_jax.options import chain_metrics
    m = chain_metrics(chain, None if start_xy is None else jnp.asarray(start_xy, jnp.float32))
    return {f"options/{k}": jnp.asarray(v, jnp.float32) for k, v in m.items()}
