"""Learning: what one DSC++ iteration learns from the experience its rollout collected.

In the paper's words (Algorithm 2, lines 13-14, at the end of an iteration rather than after
every execution; Algorithm 3, lines 7-9; Algorithm 1)::

    td3, m  = update_policies(...)   # Alg. 2 l. 14: TD3 + HER on the shared replay (one TD3
                                     #   per option: update_option_policies)
    dyn, m  = update_dynamics(...)   # f_xi on the model replay (model-based algorithms)
    chain   = refit(...)             # Alg. 2 l. 13: refit the classifiers of the options that
                                     #   received examples
    chain   = grow_chain(...)        # Alg. 3 l. 7-9: maturity; a new option while no option's
                                     #   initiation set holds the start state
    table   = dp_value_table(...)    # Alg. 1 CREATE-VALUE-TABLE (DP subgoals only)

With one TD3 per option (`Config.per_option_td3`: the baselines dsc and dual, whose region
policies see the observation alone, and mf_dscpp with shared_critic=false) each option learns
from its own transitions, the global option from all of them, and a new option starts as a copy
of the global option's networks (`init_new_options`, after the chain grew).

`learn` runs them in that order on a `trainer.TrainState`. Every function is pure and jit-able;
``seed_axis`` names the vmap axis of a seed group, so that work only some runs need runs when any
run needs it instead of on every call.
"""
from __future__ import annotations

from typing import Any, Dict, Tuple

import jax
import jax.numpy as jnp

from dscpp_jax import frontier
from dscpp_jax.acting import FRONTIER_KEY_SALT, any_seed, chain_metrics, frontier_candidates, \
    option_table, value_fn
from dscpp_jax.config import Config
from dscpp_jax.dynamics import dynamics_fit_normaliser, dynamics_init, dynamics_train
from dscpp_jax.her import HERBuffer, her_index, her_relabel, her_sample
from dscpp_jax.options import FREE, grow_chain as _grow_chain, mature_options, refit as _refit
from dscpp_jax.replay import (Replay, Transition, replay_gather, replay_group_index,
                              replay_group_sample_index, replay_recent, replay_sample_index)
from dscpp_jax.subgoals import dp_value_table as _dp_value_table
from dscpp_jax.td3 import (td3_copy_option, td3_option, td3_set_option, td3_updates,
                           td3_updates_options)
from dscpp_jax.dynamics import DynamicsConfig
from dscpp_jax.td3 import TD3Config

GLOBAL_ROW = 0   # the global option's row of the option table (acting.GLOBAL_OPTION)


# ------------------------------------------------------------------------------------------------
# Option policies: TD3 + HER
# ------------------------------------------------------------------------------------------------
def her_max_segment(config: Config) -> int:
    """The longest HER segment: an option's execution (the episode for the flat algorithms)."""
    return config.chain.option_timeout if config.hierarchical else config.task.episode_length


def td3_buffer(config: Config, replay: Replay) -> Any:
    """The replay as TD3's minibatches are drawn from it in one learning phase: indexed once
    (``her.her_index``), so that each draw of ``td3_sample_fn`` is a few gathers."""
    return her_index(replay, her_max_segment(config))


def td3_sample_fn(config: Config, env: Any = None) -> Any:
    """``sample_fn(key, replay, n) -> Transition`` for TD3: HER relabelling within an option's
    segment (the episode's for the flat algorithms). ``replay`` is a Replay or its
    :func:`td3_buffer` (the same draws, cheaper). ``env`` is unused (kept for callers)."""
    max_seg = her_max_segment(config)

    def sample_fn(k, buf, n):
        return her_sample(k, buf, n, strategy=config.td3.her_strategy,
                          relabel_prob=config.td3.her_relabel_prob, max_segment=max_seg,
                          goal_tolerance=config.task.goal_tolerance)

    return sample_fn


def update_policies(config: Config, td3, replay: Replay, key, seed_axis=None
                    ) -> Tuple[Any, Dict[str, jax.Array]]:
    """The iteration's TD3 steps. The shared goal-conditioned TD3 (DSC++): `config.td3_updates`
    steps on HER-relabelled minibatches of the replay. One TD3 per option
    (`config.per_option_td3`): `update_option_policies`. Returns (td3, ``td3/*`` metrics)."""
    tcfg = TD3Config.from_section(config.td3, config.model_based)
    if config.per_option_td3:
        return update_option_policies(config, td3, replay, key, seed_axis)
    td3, tm = td3_updates(tcfg, td3, td3_buffer(config, replay), key, config.td3_updates,
                          td3_sample_fn(config), sample_block=config.td3.sample_block,
                          seed_axis=seed_axis)
    return td3, {f"td3/{k}": v for k, v in tm.items()}


def option_steps(config: Config, replay: Replay) -> jax.Array:
    """(K,) int32 gradient steps of each option's own TD3 this iteration: one per transition the
    option collected in this iteration's rollout (times `td3_updates_per_step`); 0 for the global
    option, whose TD3 learns from every transition (`update_option_policies`). As the authors'
    per-option learners, which take one TD3 step per own transition (``MFOptionClass.py``
    ``experience_replay``: ``self.solver.step``; ``MBOptionClass.py`` ``update_value_function``)."""
    K = config.chain.max_options
    ids = replay.data.option
    new = replay_recent(replay, config.run.steps_per_iter) & (ids >= 0) & (ids < K)
    n_new = jnp.bincount(jnp.where(new, ids, K).reshape(-1), length=K + 1)[:K]
    steps = jnp.round(n_new.astype(jnp.float32) * config.td3.updates_per_step).astype(jnp.int32)
    return steps.at[GLOBAL_ROW].set(0)


def region_batch(replay: Replay, rows, envs, done) -> Transition:
    """The stored steps at (rows, envs) as a region policy's minibatch: reward -1, and 0 with no
    bootstrap where ``done`` ((rows, envs)-shaped bool of the replay, e.g. ``in_target``) holds;
    an empty goal (the policies see the observation alone). Time-outs and episode ends bootstrap
    (``MFOptionClass.py`` ``experience_replay``: ``done = self.is_term_true(next_state)``)."""
    steps = replay_gather(replay, rows, envs)
    d = done[rows, envs].astype(jnp.float32)
    return Transition(obs=steps.obs, action=steps.action, reward=-(1.0 - d),
                      next_obs=steps.next_obs, goal=jnp.zeros(steps.obs.shape[:-1] + (0,),
                                                               steps.obs.dtype),
                      discount=1.0 - d)


def option_sample_fns(config: Config, replay: Replay):
    """(own, everything): ``own(key, k, n)`` draws option k's minibatch from its own transitions,
    ``everything(key, n)`` the global option's from every transition.

    Region policies (dsc, dual; ``MFOptionClass.py`` ``experience_replay``): an option's reward is
    its target region's (`region_batch` on ``in_target``); the global option's, on every option's
    transitions, the task's (``at_goal``: ``global_reward``, ``global_done``). No HER.

    Goal-conditioned per-option policies (``MBOptionClass.py`` ``update_value_function``): HER
    (`td3_sample_fn`) within the option's own segments; the global option relabels every
    transition the same way (the authors step it with the same two goal copies)."""
    index = replay_group_index(replay, replay.data.option, config.chain.max_options)
    if config.option_policies == "region":
        def own(k, o, n):
            rows, envs = replay_group_sample_index(replay, index, k, o, n)
            return region_batch(replay, rows, envs, replay.data.in_target)

        def everything(k, n):
            rows, envs = replay_sample_index(replay, k, n)
            return region_batch(replay, rows, envs, replay.data.at_goal)
        return own, everything
    hb: HERBuffer = td3_buffer(config, replay)
    sample = td3_sample_fn(config)

    def own_her(k, o, n):
        k_idx, k_fut, k_rel = jax.random.split(k, 3)
        rows, envs = replay_group_sample_index(replay, index, k_idx, o, n)
        return her_relabel(hb, rows, envs, jax.random.uniform(k_fut, (n,)),
                           jax.random.uniform(k_rel, (n,)), config.td3.her_strategy,
                           config.td3.her_relabel_prob, her_max_segment(config),
                           config.task.goal_tolerance)
    return own_her, lambda k, n: sample(k, hb, n)


def update_option_policies(config: Config, td3, replay: Replay, key, seed_axis=None
                           ) -> Tuple[Any, Dict[str, jax.Array]]:
    """One TD3 per option slot (`config.per_option_td3`): each option's TD3 takes `option_steps`
    steps on minibatches of its own transitions (`td3.td3_updates_options`, at most
    `config.td3_updates` steps in all), and the global option's (row 0) `config.td3_updates`
    steps on minibatches of every transition (`option_sample_fns`): about twice the shared TD3's
    work. When `config.td3_updates` is a whole number of `td3.sample_block` blocks the global
    option's blocks run beside the options' in one pass (`td3_updates_options` with
    ``global_row``: the same steps as one after the other). Returns (td3, ``td3/*`` metrics of
    the options' steps, ``td3/global_*`` of the global option's)."""
    tcfg = TD3Config.from_section(config.td3, config.model_based)
    block = config.td3.sample_block
    own, everything = option_sample_fns(config, replay)
    k_own, k_glob = jax.random.split(key)
    rounds = -(-config.td3_updates // block)
    steps = option_steps(config, replay)
    if config.td3_updates % block == 0:
        td3, m = td3_updates_options(tcfg, td3, steps, k_own, rounds, own, sample_block=block,
                                     seed_axis=seed_axis, global_row=GLOBAL_ROW,
                                     global_key=k_glob, global_sample_fn=everything)
        return td3, {f"td3/{k}": v for k, v in m.items()}
    td3, om = td3_updates_options(tcfg, td3, steps, k_own, rounds, own, sample_block=block,
                                  seed_axis=seed_axis)
    glob, gm = td3_updates(tcfg, td3_option(td3, GLOBAL_ROW), None, k_glob, config.td3_updates,
                           lambda k, _, n: everything(k, n), sample_block=block,
                           seed_axis=seed_axis)
    td3 = td3_set_option(td3, GLOBAL_ROW, glob)
    metrics = {f"td3/{k}": v for k, v in om.items()}
    metrics.update({f"td3/global_{k}": v for k, v in gm.items()})
    return td3, metrics


def init_new_options(config: Config, td3, status_before, status_after):
    """The per-option TD3s after the chain grew from `status_before` to `status_after` ((K,)
    option statuses): with ``option_init="copy_global"`` each option created in between starts as
    a copy of the global option's networks (`td3.td3_copy_option`: fresh optimiser state), as
    the authors' ``initialize_value_function_with_global_value_function`` (``MBOptionClass.py``,
    and ``MFOptionClass.py`` in the versions where it is called; DSC's ``OptionClass.py``
    ``initialize_with_global_ddpg``); "random" leaves them as initialised. The goal option exists
    from the start and is never copied (the authors' parent-None option)."""
    if not config.per_option_td3 or config.chain.option_init != "copy_global":
        return td3
    created = (status_before == FREE) & (status_after != FREE)
    return td3_copy_option(TD3Config.from_section(config.td3, config.model_based), td3,
                           GLOBAL_ROW, created)


# ------------------------------------------------------------------------------------------------
# The dynamics model f_xi (model-based algorithms)
# ------------------------------------------------------------------------------------------------
def init_dynamics(key, obs_dim: int, act_dim: int, config: Config):
    """A fresh dynamics ensemble for `config`."""
    return dynamics_init(key, obs_dim, act_dim, DynamicsConfig.from_section(config.dynamics))


def fit_normaliser(config: Config, dyn, model_replay: Replay):
    """The model's input and output statistics refit on the model replay."""
    obs, act, nxt = model_replay.data
    return dynamics_fit_normaliser(dyn, obs, act, nxt, model_replay.valid,
                                   cfg=DynamicsConfig.from_section(config.dynamics))


def dynamics_updates(config: Config, dyn, model_replay: Replay, key, num_steps: int):
    """`num_steps` Adam steps of the model on the model replay. Returns (dyn, {loss,
    loss_last})."""
    obs, act, nxt = model_replay.data
    dyn, m = dynamics_train(DynamicsConfig.from_section(config.dynamics), dyn,
                            (obs, act, nxt, model_replay.valid), key, int(num_steps))
    return dyn, {"loss": jnp.mean(m["loss"]), "loss_last": m["loss"][-1]}


def update_dynamics(config: Config, dyn, model_replay: Replay, counters, key, key_pretrain,
                    seed_axis=None):
    """The iteration's model steps, and once the warm-up data is in, one longer burst of
    `config.dynamics.pretrain_steps` (the original's 50 epochs on the random rollouts). Returns
    (dyn, counters with ``warmup_done``, ``dynamics/*`` metrics)."""
    warmup = counters.episodes < config.task.warmup_episodes
    dyn = fit_normaliser(config, dyn, model_replay)
    dyn, dm = dynamics_updates(config, dyn, model_replay, key, config.dyn_updates)
    do_pre = (~warmup) & (~counters.warmup_done)
    if config.dynamics.pretrain_steps > 0:
        def pretrain(d):
            new = dynamics_updates(config, d, model_replay, key_pretrain,
                                   config.dynamics.pretrain_steps)[0]
            return jax.tree_util.tree_map(lambda a, b: jnp.where(do_pre, a, b), new, d)
        dyn = jax.lax.cond(any_seed(do_pre, seed_axis), pretrain, lambda d: d, dyn)
    counters = counters.replace(warmup_done=counters.warmup_done | do_pre)
    return dyn, counters, {f"dynamics/{k}": v for k, v in dm.items()}


# ------------------------------------------------------------------------------------------------
# The skill chain
# ------------------------------------------------------------------------------------------------
def refit(config: Config, chain, seed_axis=None):
    """Refit the initiation classifiers of the options that received examples
    (`options.refit`)."""
    return _refit(chain, seed_axis=seed_axis)


def grow_chain(config: Config, chain, start_xy, is_open=None):
    """Maturity and chain growth (`options.grow_chain`); with `is_open` (the rows whose frontier
    is open) the frontier's parents and re-targeting (`frontier.grow_chain`)."""
    if is_open is None:
        return _grow_chain(chain, start_xy)
    return frontier.grow_chain(chain, start_xy, is_open)


def dp_value_table(config: Config, chain, td3):
    """Algorithm 1's value table over the chain, valued with the shared critic or each option's
    own (`subgoals.dp_value_table`)."""
    if not config.per_option_td3:
        return _dp_value_table(chain, value_fn(config, td3), gamma=config.mpc.discount)
    # each option's row of the table is valued with its own critic
    return _dp_value_table(chain, None, gamma=config.mpc.discount,
                           option_value_fn=lambda k, s, g: value_fn(config, td3, k)(s, g))


def update_chain(config: Config, env, chain, td3, dp_table, key, seed_axis=None):
    """Refit, grow (with the frontier's parents when `config.frontier.parent` is set; its
    candidates drawn with `key` folded with `FRONTIER_KEY_SALT`) and, for DP subgoals, rebuild
    the value table. Returns (chain, dp_table, ``frontier/*`` and ``options/*`` metrics)."""
    metrics: Dict[str, jax.Array] = {}
    start = jnp.asarray(env.start, jnp.float32)
    chain = refit(config, chain, seed_axis)
    if config.frontier.parent:
        cand = frontier_candidates(config, env, jax.random.fold_in(key, FRONTIER_KEY_SALT))
        chain = mature_options(chain)
        # growth leaves mature rows as they are, so this holds for the grown chain too
        is_open = frontier.open_rows(frontier.frontier_probe(chain, cand, config.frontier.radius),
                                     config.frontier.min_open)
        g0, p0 = frontier.gestation_row(chain), chain.parent
        chain = grow_chain(config, chain, start, is_open)
        g = frontier.gestation_row(chain)
        gc = jnp.clip(g, 0)
        metrics["frontier/retargeted"] = ((g >= 0) & (g == g0)
                                          & (chain.parent[gc] != p0[gc])).astype(jnp.float32)
        metrics["frontier/open_rows"] = jnp.sum(is_open).astype(jnp.float32)
    else:
        chain = grow_chain(config, chain, start)
    if config.subgoal == "dp":
        dp_table = dp_value_table(config, chain, td3)
    metrics.update(chain_metrics(config, chain, env.start))
    metrics.update(option_table(chain))
    return chain, dp_table, metrics


# ------------------------------------------------------------------------------------------------
# One learning phase
# ------------------------------------------------------------------------------------------------
def all_finite(tree) -> jax.Array:
    """Scalar bool: every floating leaf of `tree` is finite."""
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)
              if hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.ones((), bool)


def learn(state: Any, env, key, seed_axis=None) -> Tuple[Any, Dict[str, jax.Array]]:
    """The learning half of one iteration on a `trainer.TrainState` (`env`: its env): policies,
    dynamics, chain, in that order; counts the iteration. Returns (state, metrics: ``td3/*``,
    ``dynamics/*``, ``frontier/*``, ``options/*``, ``finite/*``)."""
    config = state.config
    k_td3, k_dyn, k_pre = jax.random.split(key, 3)
    metrics: Dict[str, jax.Array] = {}

    # UPDATE OPTION POLICIES (TD3 + HER)
    td3, tm = update_policies(config, state.td3, state.replay, k_td3, seed_axis)
    metrics.update(tm)
    finite = {"td3": all_finite(td3)}

    # UPDATE THE DYNAMICS MODEL
    dyn, counters = state.dyn, state.counters
    if config.model_based:
        dyn, counters, dm = update_dynamics(config, dyn, state.model_replay, counters, k_dyn,
                                            k_pre, seed_axis)
        metrics.update(dm)
        finite["dynamics"] = all_finite(dyn)

    # REFIT CLASSIFIERS, GROW THE CHAIN, REBUILD THE DP TABLE
    chain, dp_table = state.chain, state.dp_table
    if config.hierarchical:
        chain, dp_table, cm = update_chain(config, env, chain, td3, dp_table, key, seed_axis)
        td3 = init_new_options(config, td3, state.chain.status, chain.status)
        metrics.update(cm)
        finite["classifiers"] = all_finite(chain.clf)

    for k, v in finite.items():
        metrics[f"finite/{k}"] = v.astype(jnp.float32)
    counters = counters.replace(iteration=counters.iteration + 1)
    state = state.replace(td3=td3, dyn=dyn, chain=chain, dp_table=dp_table, counters=counters)
    return state, metrics
