"""Goal-conditioned TD3 (Fujimoto et al. 2018) as pure functions over a typed state.

Inputs are the observation concatenated with a goal xy. Twin critics with clipped double-Q
targets, target policy smoothing, delayed actor and target updates (one compiled function: the
actor/target step sits behind ``lax.cond``). Sparse reward 0/-1 and the continuation flag come
with the batch (see :class:`dscpp_jax.replay.Transition`; :mod:`dscpp_jax.her` builds them).

Typical use::

    cfg = TD3Config.model_free()
    state = td3_init(key, obs_dim, 2, action_dim, cfg)
    update = jax.jit(td3_update, static_argnums=0)
    state, metrics = update(cfg, state, batch, key)
    values = td3_value(cfg, state, obs, goal)          # min(Q1, Q2)(s, g, pi(s, g))

One TD3 per option (``Config.per_option_td3``): :func:`td3_init_per_option` stacks
independent states on a leading option axis, :func:`td3_option` picks one out (per env under a
vmap) and :func:`td3_set_option` writes one back, :func:`td3_copy_option` starts new options as
copies of another (the global option's), and :func:`td3_updates_options` gives each option a
given number of gradient steps on minibatches of its own data.

All functions take the frozen config as their first (static) argument; jit them with
``static_argnums=0`` or call them inside your own jitted code.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Dict, Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import optax

from dscpp_jax.config import TD3Section
from dscpp_jax.networks import Actor, QNetwork, TwinCritic, actor_action_dim, first_head
from dscpp_jax.replay import Transition

PyTree = Any
TD3_DTYPES = ("float32", "bfloat16")   # TD3Config.compute_dtype's choices


@dataclasses.dataclass(frozen=True)
class TD3Config:
    """TD3 hyperparameters (static; hashable so it can be a jit static argument).

    Defaults follow Fujimoto et al. (2018) and the paper's appendix tables 1-2, except
    ``batch_size``: the authors' code used 256 while the paper's table says 100; pass
    ``batch_size=100`` to reproduce the table. (A run builds its TD3Config from the config's
    ``td3`` section, ``TD3Config.from_section``, whose ``td3.batch_size``, flat
    ``td3_batch_size``, is the table's 100 unless a preset or ``--set`` changes it.)
    """

    actor_lr: float = 3e-4
    critic_lr: float = 3e-4
    discount: float = 0.99  # gamma
    tau: float = 0.005  # target update rate
    policy_noise: float = 0.2  # target policy smoothing std (times max_action)
    noise_clip: float = 0.5  # smoothing noise clip (times max_action)
    policy_delay: int = 2  # one actor + target update every `policy_delay` critic updates
    batch_size: int = 256
    hidden: Tuple[int, ...] = (256, 256)
    output_normalisation: bool = False  # linear actor output / max(1, mean|a|) instead of tanh
    max_action: float = 1.0
    exploration_noise: float = 0.1  # Gaussian std added to the actor's action when exploring
    # Probability of a uniform-random action when exploring: `random_action_prob_start` until the
    # agent has `random_action_switch_successes` successes, then `random_action_prob`
    # (see td3_random_prob; the model-free schedule of the original is 0.8 -> 0.2 after 3).
    random_action_prob: float = 0.2
    random_action_prob_start: float = 0.8
    random_action_switch_successes: int = 3
    replay_capacity: int = 1_000_000
    # Clip TD targets to [lo, hi] (None: no clipping). With rewards in {-1, 0} every true value
    # lies in [-1 / (1 - discount), 0]; clipping there (as HER implementations do) stops the
    # critic from bootstrapping off values that no policy can have.
    target_range: Optional[Tuple[float, float]] = None
    # Weight of an L2 penalty on the actor's actions, ``action_l2 * mean((pi(s, g) / max_action)^2)``
    # added to the actor loss (0: off, as in the original). OpenAI Baselines' HER uses 1.0: it keeps
    # the deterministic policy off its saturated, bang-bang corners.
    action_l2: float = 0.0
    # Matmul operands and activations of the actor and critics: "float32", or "bfloat16": the hidden
    # activations and the products between hidden layers in bf16; the first layer's product and
    # the output layer in float32, so that raw positions and Q values (down to -1 / (1 - discount))
    # keep their resolution. Parameters, optimiser state, losses and TD targets stay float32.
    compute_dtype: str = "float32"

    def __post_init__(self):
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))
        if self.target_range is not None:
            lo, hi = (float(v) for v in self.target_range)
            if not lo < hi:
                raise ValueError(f"TD3Config.target_range must be (lo, hi) with lo < hi, got "
                                 f"{self.target_range}")
            object.__setattr__(self, "target_range", (lo, hi))
        if self.policy_delay < 1:
            raise ValueError(f"TD3Config.policy_delay must be >= 1, got {self.policy_delay}")
        if self.batch_size < 1:
            raise ValueError(f"TD3Config.batch_size must be >= 1, got {self.batch_size}")
        if not self.hidden or min(self.hidden) < 1:
            raise ValueError(f"TD3Config.hidden must be positive layer widths, got {self.hidden}")
        if not 0.0 <= self.tau <= 1.0:
            raise ValueError(f"TD3Config.tau must be in [0, 1], got {self.tau}")
        if not 0.0 <= self.discount <= 1.0:
            raise ValueError(f"TD3Config.discount must be in [0, 1], got {self.discount}")
        if self.compute_dtype not in TD3_DTYPES:
            raise ValueError(f"TD3Config.compute_dtype must be one of {TD3_DTYPES}, got "
                             f"{self.compute_dtype!r}")
        if not self.action_l2 >= 0.0:
            raise ValueError(f"TD3Config.action_l2 must be >= 0, got {self.action_l2}")
        for name in ("random_action_prob", "random_action_prob_start"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"TD3Config.{name} must be a probability, got {p}")

    @classmethod
    def model_based(cls, **overrides) -> "TD3Config":
        """Paper table 1: lr 1e-5, output normalisation, random-action probability 0.1."""
        kw = dict(
            actor_lr=1e-5,
            critic_lr=1e-5,
            output_normalisation=True,
            random_action_prob=0.1,
            random_action_prob_start=0.1,
            random_action_switch_successes=0,
        )
        kw.update(overrides)
        return cls(**kw)

    @classmethod
    def from_section(cls, section: TD3Section, model_based: bool) -> "TD3Config":
        """The TD3 (+ HER) learner a run config's `td3` section sets: the paper's table 1
        (`model_based`) or 2 with the section's sizes, rates and exploration."""
        lr = section.effective_lr(model_based)
        kw = dict(batch_size=section.batch_size, hidden=(section.hidden, section.hidden),
                  discount=section.discount, exploration_noise=section.action_noise,
                  replay_capacity=section.replay_capacity, actor_lr=lr, critic_lr=lr,
                  action_l2=section.action_l2, compute_dtype=section.dtype)
        if section.clip_targets:   # the value range under the 0 / -1 reward
            kw.update(target_range=(-1.0 / (1.0 - section.discount), 0.0))
        if section.random_action_prob >= 0:
            kw.update(random_action_prob=section.random_action_prob)
            if model_based:
                kw.update(random_action_prob_start=section.random_action_prob)
        if not model_based:
            kw.update(random_action_prob_start=section.mf_initial_random_prob,
                      random_action_switch_successes=section.mf_random_decay_successes)
        return (cls.model_based if model_based else cls.model_free)(**kw)

    @classmethod
    def model_free(cls, **overrides) -> "TD3Config":
        """Paper table 2: lr 3e-4, tanh actor, random-action probability 0.8 -> 0.2 after 3 successes."""
        kw = dict(
            actor_lr=3e-4,
            critic_lr=3e-4,
            output_normalisation=False,
            random_action_prob=0.2,
            random_action_prob_start=0.8,
            random_action_switch_successes=3,
        )
        kw.update(overrides)
        return cls(**kw)


@flax.struct.dataclass
class TD3State:
    actor_params: PyTree
    critic_params: PyTree
    target_actor_params: PyTree
    target_critic_params: PyTree
    actor_opt_state: PyTree
    critic_opt_state: PyTree
    step: jax.Array  # int32: critic updates done so far


def _dtypes(cfg: TD3Config):
    """(dtype, io_dtype) of the networks for ``cfg.compute_dtype``."""
    return {"float32": (None, None), "bfloat16": (jnp.bfloat16, jnp.float32)}[cfg.compute_dtype]


def _actor(cfg: TD3Config, action_dim: int) -> Actor:
    dtype, io_dtype = _dtypes(cfg)
    return Actor(
        action_dim=action_dim,
        hidden=cfg.hidden,
        output_normalisation=cfg.output_normalisation,
        max_action=cfg.max_action,
        dtype=dtype,
        io_dtype=io_dtype,
    )


def _critic(cfg: TD3Config) -> TwinCritic:
    dtype, io_dtype = _dtypes(cfg)
    return TwinCritic(hidden=cfg.hidden, dtype=dtype, io_dtype=io_dtype)


def _actor_tx(cfg: TD3Config) -> optax.GradientTransformation:
    return optax.adam(cfg.actor_lr)


def _critic_tx(cfg: TD3Config) -> optax.GradientTransformation:
    return optax.adam(cfg.critic_lr)


def td3_init(key: jax.Array, obs_dim: int, goal_dim: int, action_dim: int, cfg: TD3Config) -> TD3State:
    """Fresh actor, twin critic, identical targets and Adam states. ``goal_dim`` 0: networks of
    the observation alone (pass goals of shape ``(..., 0)``), as the baseline DSC's option
    policies."""
    for name, v in (("obs_dim", obs_dim), ("action_dim", action_dim)):
        if int(v) < 1:
            raise ValueError(f"td3_init: {name} must be >= 1, got {v}")
    if int(goal_dim) < 0:
        raise ValueError(f"td3_init: goal_dim must be >= 0 (0: no goal input), got {goal_dim}")
    ka, kc = jax.random.split(key)
    obs = jnp.zeros((1, obs_dim), jnp.float32)
    goal = jnp.zeros((1, goal_dim), jnp.float32)
    act = jnp.zeros((1, action_dim), jnp.float32)
    actor_params = _actor(cfg, action_dim).init(ka, obs, goal)
    critic_params = _critic(cfg).init(kc, obs, goal, act)
    return TD3State(
        actor_params=actor_params,
        critic_params=critic_params,
        target_actor_params=actor_params,
        target_critic_params=critic_params,
        actor_opt_state=_actor_tx(cfg).init(actor_params),
        critic_opt_state=_critic_tx(cfg).init(critic_params),
        step=jnp.zeros((), jnp.int32),
    )


def _pi(cfg: TD3Config, actor_params: PyTree, obs: jax.Array, goal: jax.Array) -> jax.Array:
    """Raw actor output (what the policy gradient differentiates)."""
    return _actor(cfg, actor_action_dim(actor_params)).apply(actor_params, obs, goal)


def _q(cfg: TD3Config, critic_params: PyTree, obs, goal, action) -> jax.Array:
    return _critic(cfg).apply(critic_params, obs, goal, action)


def _q1(cfg: TD3Config, critic_params: PyTree, obs, goal, action) -> jax.Array:
    """The first head alone, ``_q(...)[0]`` at half the work (the actor's loss uses only Q1)."""
    dtype, io_dtype = _dtypes(cfg)
    return QNetwork(hidden=cfg.hidden, dtype=dtype, io_dtype=io_dtype).apply(
        first_head(critic_params), obs, goal, action)


def td3_act(cfg: TD3Config, actor_params: PyTree, obs: jax.Array, goal: jax.Array) -> jax.Array:
    """Deterministic action pi(obs, goal), clipped to [-max_action, max_action]; any batch shape."""
    a = _pi(cfg, actor_params, obs, goal)
    return jnp.clip(a, -cfg.max_action, cfg.max_action)


def td3_random_prob(cfg: TD3Config, num_successes: jax.Array) -> jax.Array:
    """Random-action probability given the number of successes so far (jit-able)."""
    return jnp.where(
        num_successes >= cfg.random_action_switch_successes,
        cfg.random_action_prob,
        cfg.random_action_prob_start,
    ).astype(jnp.float32)


def td3_explore(
    cfg: TD3Config,
    actor_params: PyTree,
    key: jax.Array,
    obs: jax.Array,
    goal: jax.Array,
    random_prob: Optional[jax.Array] = None,
    noise_std: Optional[jax.Array] = None,
) -> jax.Array:
    """Exploration action: pi + N(0, noise_std), clipped; uniform random with prob ``random_prob``.

    ``random_prob`` defaults to ``cfg.random_action_prob`` and ``noise_std`` to
    ``cfg.exploration_noise`` (both times ``max_action``); either may be a traced scalar or an
    array broadcastable to the batch shape ``obs.shape[:-1]``.
    """
    return td3_perturb(cfg, td3_act(cfg, actor_params, obs, goal), key, random_prob, noise_std)


def td3_perturb(
    cfg: TD3Config,
    a: jax.Array,
    key: jax.Array,
    random_prob: Optional[jax.Array] = None,
    noise_std: Optional[jax.Array] = None,
) -> jax.Array:
    """The exploration of :func:`td3_explore` applied to given deterministic actions ``a``
    (batch shape ``a.shape[:-1]``), e.g. actions of per-option actors gathered per env."""
    p = cfg.random_action_prob if random_prob is None else random_prob
    sigma = cfg.exploration_noise if noise_std is None else noise_std
    kn, ku, kr = jax.random.split(key, 3)
    sigma = jnp.asarray(sigma, a.dtype)[..., None] if jnp.ndim(sigma) else sigma
    noisy = a + cfg.max_action * sigma * jax.random.normal(kn, a.shape, a.dtype)
    noisy = jnp.clip(noisy, -cfg.max_action, cfg.max_action)
    rand = jax.random.uniform(ku, a.shape, a.dtype, -cfg.max_action, cfg.max_action)
    use_rand = jax.random.uniform(kr, a.shape[:-1]) < p
    return jnp.where(use_rand[..., None], rand, noisy)


def td3_value(cfg: TD3Config, state: TD3State, obs: jax.Array, goal: jax.Array) -> jax.Array:
    """V(s | g) = min(Q1, Q2)(s, g, pi(s, g)) with the online networks; shape ``obs.shape[:-1]``."""
    a = td3_act(cfg, state.actor_params, obs, goal)
    return jnp.min(_q(cfg, state.critic_params, obs, goal, a), axis=0)


def td3_target_noise(cfg: TD3Config, key: jax.Array, shape: Tuple[int, ...]) -> jax.Array:
    """Target policy smoothing noise: clip(N(0, policy_noise), -noise_clip, noise_clip) * max_action."""
    eps = cfg.policy_noise * jax.random.normal(key, shape)
    return cfg.max_action * jnp.clip(eps, -cfg.noise_clip, cfg.noise_clip)


def td3_targets(cfg: TD3Config, state: TD3State, batch: Transition, noise: jax.Array) -> jax.Array:
    """Clipped double-Q TD targets ``r + gamma * c * min_i Q'_i(s', g, clip(pi'(s', g) + noise))``
    (Fujimoto et al. 2018; the regression targets of :func:`td3_critic_loss`).

    ``c = batch.discount`` is the continuation flag (0 at the goal). With ``cfg.target_range``
    the targets are clipped to that interval. Pure; shape ``(B,)``.
    """
    a_next = _pi(cfg, state.target_actor_params, batch.next_obs, batch.goal)
    a_next = jnp.clip(a_next + noise, -cfg.max_action, cfg.max_action)
    q_next = jnp.min(_q(cfg, state.target_critic_params, batch.next_obs, batch.goal, a_next), axis=0)
    y = batch.reward + cfg.discount * batch.discount * q_next
    if cfg.target_range is not None:
        y = jnp.clip(y, cfg.target_range[0], cfg.target_range[1])
    return y


def td3_critic_loss(cfg: TD3Config, critic_params: PyTree, batch: Transition, y: jax.Array
                    ) -> Tuple[jax.Array, jax.Array]:
    """TD3's critic loss (Fujimoto et al. 2018, clipped double Q-learning): the sum over the twin
    heads of the mean squared error to the shared targets ``y`` = :func:`td3_targets`,
    ``sum_i mean_B (Q_i(s, g, a) - y)^2``. The reward in ``y`` is the paper's option reward
    (appendix, "Policy learning"): 0 on reaching the goal ``g`` and -1 otherwise, with ``g``
    relabelled by HER. Returns (loss, the heads' Q values (2, B))."""
    q = _q(cfg, critic_params, batch.obs, batch.goal, batch.action)  # (2, B)
    return jnp.sum(jnp.mean(jnp.square(q - y[None]), axis=-1)), q


def td3_actor_loss(cfg: TD3Config, actor_params: PyTree, critic_params: PyTree,
                   batch: Transition) -> jax.Array:
    """TD3's deterministic policy-gradient loss ``-mean_B Q_1(s, g, pi(s, g))``: the goal-
    conditioned option policy ``pi_o(s | g) = argmax_a Q(s, a | g)`` of the paper's appendix
    ("Learning a single value function"); plus ``action_l2 * mean (a / max_action)^2`` when
    ``cfg.action_l2 > 0``."""
    a = _pi(cfg, actor_params, batch.obs, batch.goal)
    loss = -jnp.mean(_q1(cfg, critic_params, batch.obs, batch.goal, a))
    if cfg.action_l2 > 0:
        loss = loss + cfg.action_l2 * jnp.mean(jnp.square(a / cfg.max_action))
    return loss


def _polyak(tau: float, target: PyTree, online: PyTree) -> PyTree:
    return jax.tree_util.tree_map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)


def td3_update(
    cfg: TD3Config, state: TD3State, batch: Transition, key: jax.Array,
    seed_axis: Optional[str] = None, actor: Optional[bool] = None,
) -> Tuple[TD3State, Dict[str, jax.Array]]:
    """One critic step; every ``policy_delay``-th call also an actor step and soft target update.

    ``actor`` (static): None decides by the step count (``step % policy_delay == 0`` after this
    step), with a ``lax.cond``; True or False takes or skips the actor step with no branch. On a
    GPU every ``lax.cond`` copies its predicate to the host and waits for the device, so loops of
    many steps place the actor steps themselves (:func:`td3_updates` does).

    ``seed_axis``: the name of an enclosing ``vmap`` axis over independent runs (seeds), if any
    (or a tuple of such names); with ``actor=None`` the actor step then runs when any run needs
    it instead of on every call."""
    noise = td3_target_noise(cfg, key, batch.action.shape)
    y = jax.lax.stop_gradient(td3_targets(cfg, state, batch, noise))

    (critic_loss, q), grads = jax.value_and_grad(
        lambda p: td3_critic_loss(cfg, p, batch, y), has_aux=True)(state.critic_params)
    updates, critic_opt_state = _critic_tx(cfg).update(grads, state.critic_opt_state, state.critic_params)
    critic_params = optax.apply_updates(state.critic_params, updates)
    step = state.step + 1

    def actor_step(operand):
        actor_params, actor_opt_state, t_actor, t_critic = operand

        loss, g = jax.value_and_grad(
            lambda p: td3_actor_loss(cfg, p, critic_params, batch))(actor_params)
        upd, actor_opt_state = _actor_tx(cfg).update(g, actor_opt_state, actor_params)
        actor_params = optax.apply_updates(actor_params, upd)
        t_actor = _polyak(cfg.tau, t_actor, actor_params)
        t_critic = _polyak(cfg.tau, t_critic, critic_params)
        return (actor_params, actor_opt_state, t_actor, t_critic), loss

    def skip(operand):
        return operand, jnp.zeros((), critic_loss.dtype)

    do_actor = step % cfg.policy_delay == 0
    operand = (state.actor_params, state.actor_opt_state, state.target_actor_params,
               state.target_critic_params)
    if actor is not None:
        do_actor = jnp.asarray(bool(actor))
        (actor_params, actor_opt_state, t_actor, t_critic), actor_loss = (
            actor_step(operand) if actor else skip(operand))
    elif seed_axis is None:
        (actor_params, actor_opt_state, t_actor, t_critic), actor_loss = jax.lax.cond(
            do_actor, actor_step, skip, operand)
    else:
        # vmapped over seeds: a batched predicate would turn the cond into a select that runs
        # the actor step every time; branch on "any seed updates" and select per seed inside
        def some(op):
            new, loss = actor_step(op)
            return jax.tree_util.tree_map(lambda a, b: jnp.where(do_actor, a, b), (new, loss),
                                          skip(op))
        any_actor = jax.lax.psum(do_actor.astype(jnp.int32), seed_axis) > 0
        (actor_params, actor_opt_state, t_actor, t_critic), actor_loss = jax.lax.cond(
            any_actor, some, skip, operand)
    new_state = state.replace(
        actor_params=actor_params,
        critic_params=critic_params,
        target_actor_params=t_actor,
        target_critic_params=t_critic,
        actor_opt_state=actor_opt_state,
        critic_opt_state=critic_opt_state,
        step=step,
    )
    metrics = {
        "critic_loss": critic_loss,
        "actor_loss": actor_loss,
        "actor_updated": do_actor.astype(jnp.float32),
        "q_mean": jnp.mean(q),
        "target_mean": jnp.mean(y),
        "reward_mean": jnp.mean(batch.reward),
    }
    return new_state, metrics


def _scan_updates(cfg: TD3Config, state: TD3State, xs: PyTree,
                  get: Callable[[PyTree], Tuple[Transition, jax.Array]],
                  seed_axis: Optional[str], placed: bool = True
                  ) -> Tuple[TD3State, Dict[str, jax.Array]]:
    """One :func:`td3_update` per entry of ``xs`` (leading axis) as one ``lax.scan``;
    ``get(x)`` gives that step's minibatch and update key.

    When the steps make whole groups of ``policy_delay``, the actor step goes on the last step of
    each group, placed statically: no ``lax.cond`` per step, which on a GPU would wait for the
    device every step. That is the step-count rule of :func:`td3_update` whenever the state's
    step count starts at a multiple of ``policy_delay``, as in training, where every call takes a
    multiple of it. Other step counts (or ``placed=False``) decide per step by the step count."""
    m = jax.tree_util.tree_leaves(xs)[0].shape[0]
    d = cfg.policy_delay
    if m % d or not placed:
        return jax.lax.scan(lambda s, x: td3_update(cfg, s, *get(x), seed_axis), state, xs)
    grouped = jax.tree_util.tree_map(lambda a: a.reshape((m // d, d) + a.shape[1:]), xs)

    def group(s, g):
        ms = []
        for j in range(d):
            batch, k = get(jax.tree_util.tree_map(lambda a: a[j], g))
            s, mj = td3_update(cfg, s, batch, k, seed_axis, actor=(j == d - 1))
            ms.append(mj)
        return s, jax.tree_util.tree_map(lambda *a: jnp.stack(a), *ms)

    state, ms = jax.lax.scan(group, state, grouped)
    return state, jax.tree_util.tree_map(lambda a: a.reshape((m,) + a.shape[2:]), ms)


def _summarise(ms: Dict[str, jax.Array]) -> Dict[str, jax.Array]:
    """Per-step metrics (leading axis: the steps) as one call's: means over the steps,
    ``actor_loss`` over the steps that updated the actor, ``actor_updates`` their number."""
    n_actor = jnp.maximum(jnp.sum(ms["actor_updated"]), 1.0)
    metrics = {k: jnp.mean(v) for k, v in ms.items() if k not in ("actor_loss", "actor_updated")}
    metrics["actor_loss"] = jnp.sum(ms["actor_loss"]) / n_actor
    metrics["actor_updates"] = jnp.sum(ms["actor_updated"])
    return metrics


def td3_updates(
    cfg: TD3Config,
    state: TD3State,
    buffer: PyTree,
    key: jax.Array,
    num_steps: int,
    sample_fn: Callable[[jax.Array, PyTree, int], Transition],
    sample_block: int = 1,
    seed_axis: Optional[str] = None,
) -> Tuple[TD3State, Dict[str, jax.Array]]:
    """``num_steps`` (static) rounds of sample + :func:`td3_update` as one ``lax.scan``.

    ``sample_fn(key, buffer, batch_size) -> Transition``, e.g.
    ``lambda k, b, n: her_sample(k, b, n, strategy="future")``. Metrics are means over the steps
    (``actor_loss`` over the steps that updated the actor).

    ``sample_block`` (static) > 1 draws the minibatches of that many consecutive steps with one
    ``sample_fn`` call and then runs the steps over them. The buffer does not change while it
    learns, so every minibatch is still an independent draw from it; only the random stream
    differs. On a GPU this turns many small gathers into a few large ones. Leftover steps
    (``num_steps % sample_block``) sample one minibatch each.
    """
    num_steps = int(num_steps)
    sample_block = int(sample_block)
    if num_steps < 1:
        raise ValueError(f"td3_updates: num_steps must be >= 1, got {num_steps}")
    if sample_block < 1:
        raise ValueError(f"td3_updates: sample_block must be >= 1, got {sample_block}")
    n = cfg.batch_size
    # a call whose steps are not whole policy_delay groups decides every step by the step count,
    # so that the next call still starts at a multiple of policy_delay when this one did not
    placed = num_steps % cfg.policy_delay == 0

    def sampled(k):    # one step's minibatch and update key from its key
        ks, ku = jax.random.split(k)
        return sample_fn(ks, buffer, n), ku

    def block_body(st, k):
        ks, ku = jax.random.split(k)
        batches = jax.tree_util.tree_map(
            lambda x: x.reshape((sample_block, n) + x.shape[1:]),
            sample_fn(ks, buffer, sample_block * n))
        return _scan_updates(cfg, st, (batches, jax.random.split(ku, sample_block)),
                             lambda bk: bk, seed_axis, placed)

    if sample_block == 1:
        state, ms = _scan_updates(cfg, state, jax.random.split(key, num_steps), sampled,
                                  seed_axis, placed)
    else:
        n_blocks, rest = divmod(num_steps, sample_block)
        k_blocks, k_rest = jax.random.split(key)
        parts = []
        if n_blocks:
            state, mb = jax.lax.scan(block_body, state, jax.random.split(k_blocks, n_blocks))
            parts.append(jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), mb))
        if rest:
            state, mr = _scan_updates(cfg, state, jax.random.split(k_rest, rest), sampled,
                                      seed_axis, placed)
            parts.append(mr)
        ms = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs), *parts)
    return state, _summarise(ms)


# ------------------------------------------------------------------------------------------------
# One TD3 per option (``Config.td3.shared_critic=False``)
# ------------------------------------------------------------------------------------------------
def td3_init_per_option(key: jax.Array, num_options: int, obs_dim: int, goal_dim: int,
                        action_dim: int, cfg: TD3Config) -> TD3State:
    """``num_options`` independent :func:`td3_init` states (one key each, split from ``key``),
    stacked on a leading option axis of every leaf."""
    num_options = int(num_options)
    if num_options < 1:
        raise ValueError(f"td3_init_per_option: num_options must be >= 1, got {num_options}")
    return jax.vmap(lambda k: td3_init(k, obs_dim, goal_dim, action_dim, cfg))(
        jax.random.split(key, num_options))


def td3_option(state: TD3State, option: jax.Array) -> TD3State:
    """Option ``option``'s TD3State out of per-option states (a traced index works; under a vmap
    over ``option`` each row gathers its own)."""
    return jax.tree_util.tree_map(lambda x: x[option], state)


def td3_set_option(state: TD3State, option: jax.Array, row: TD3State) -> TD3State:
    """Per-option states with option ``option``'s (a traced index works) replaced by ``row``."""
    return jax.tree_util.tree_map(lambda a, b: a.at[option].set(b), state, row)


def td3_copy_option(cfg: TD3Config, state: TD3State, source: int, dest: jax.Array) -> TD3State:
    """Per-option states whose rows where ``dest`` ((K,) bool) holds become copies of row
    ``source``'s actor, critic and target networks, with fresh Adam states and step count 0.

    This is how the authors start a new option's learner from the global option's
    (``initialize_value_function_with_global_value_function`` in ``MFOptionClass.py`` and
    ``MBOptionClass.py``, ``initialize_with_global_ddpg`` in DSC's ``OptionClass.py``): the
    networks are copied, the optimiser state and the replay are not."""
    src = td3_option(state, source)
    fresh = src.replace(actor_opt_state=_actor_tx(cfg).init(src.actor_params),
                        critic_opt_state=_critic_tx(cfg).init(src.critic_params),
                        step=jnp.zeros((), jnp.int32))
    dest = jnp.asarray(dest, bool)
    return jax.tree_util.tree_map(
        lambda a, b: jnp.where(dest.reshape(dest.shape + (1,) * (a.ndim - 1)), b[None], a),
        state, fresh)


def option_rounds(steps: jax.Array, block: int, num_rounds: int) -> Tuple[jax.Array, jax.Array]:
    """The rounds of :func:`td3_updates_options`: (option of each round (R,) int32, the round
    runs (R,) bool). Option k gets ``round(steps[k] / block)`` rounds of ``block`` steps, in
    option order; rounds beyond the total (or beyond ``num_rounds``, which then cut the last
    options short) do not run."""
    steps = jnp.asarray(steps, jnp.int32)
    blocks = (steps + block // 2) // int(block)
    cum = jnp.cumsum(blocks)
    i = jnp.arange(int(num_rounds), dtype=jnp.int32)
    option = jnp.minimum(jnp.searchsorted(cum, i, side="right"), steps.shape[0] - 1)
    return option.astype(jnp.int32), i < cum[-1]


def td3_updates_options(
    cfg: TD3Config,
    state: TD3State,
    steps: jax.Array,
    key: jax.Array,
    num_rounds: int,
    sample_fn: Callable[[jax.Array, jax.Array, int], Transition],
    sample_block: int = 1,
    seed_axis: Optional[str] = None,
    global_row: Optional[int] = None,
    global_key: Optional[jax.Array] = None,
    global_sample_fn: Optional[Callable[[jax.Array, int], Transition]] = None,
) -> Tuple[TD3State, Dict[str, jax.Array]]:
    """Per-option TD3s (:func:`td3_init_per_option`) where option ``k`` takes about ``steps[k]``
    ((K,) int, traced) gradient steps, each on a minibatch ``sample_fn(key, k, n)`` of its own
    transitions.

    The steps run in at most ``num_rounds`` (static) rounds of ``sample_block`` (static) steps of
    one option (:func:`option_rounds`): a ``lax.scan`` over rounds, each gathering its option's
    state, running :func:`td3_update` ``sample_block`` times and writing it back. A round that
    does not run is skipped by a ``lax.cond`` (under a seed vmap, ``seed_axis``: when no run of
    the group runs it), so the cost follows the steps taken, not ``num_rounds``.

    With ``global_row`` (static), ``global_key`` and ``global_sample_fn(key, n)``, the option in
    that row (which then takes no option steps) also takes ``num_rounds * sample_block`` steps on
    minibatches of ``global_sample_fn``: the same steps, minibatches and keys as
    :func:`td3_updates` (``td3_updates(cfg, td3_option(state, global_row), None, global_key,
    num_rounds * sample_block, lambda k, _, n: global_sample_fn(k, n), sample_block)``) after
    this call without them, but each of its blocks runs beside that round's option block in one
    ``vmap`` over the pair, so the two learners take one sequence of small steps instead of two.
    Its metrics come back prefixed ``global_``, as :func:`td3_updates` names them.

    Metrics: means over the steps taken (0 when none); ``actor_updates`` and ``option_steps``
    count the actor and critic steps; ``options_learning`` the options that took any."""
    num_rounds, block = int(num_rounds), int(sample_block)
    if num_rounds < 1:
        raise ValueError(f"td3_updates_options: num_rounds must be >= 1, got {num_rounds}")
    if block < 1:
        raise ValueError(f"td3_updates_options: sample_block must be >= 1, got {block}")
    with_global = global_row is not None
    if with_global and (global_key is None or global_sample_fn is None):
        raise ValueError("td3_updates_options: global_row needs global_key and global_sample_fn")
    K = jax.tree_util.tree_leaves(state)[0].shape[0]
    n = cfg.batch_size
    if with_global:
        steps = jnp.asarray(steps, jnp.int32).at[int(global_row)].set(0)
    option, runs = option_rounds(steps, block, num_rounds)
    zero = {k: jnp.zeros((block,), jnp.float32) for k in
            ("critic_loss", "actor_loss", "actor_updated", "q_mean", "target_mean",
             "reward_mean")}
    identity = lambda bk: bk   # noqa: E731  (xs already hold each step's (minibatch, key))

    def own_inputs(kk, k):
        k_s, k_u = jax.random.split(kk)
        batches = jax.tree_util.tree_map(lambda x: x.reshape((block, n) + x.shape[1:]),
                                         sample_fn(k_s, k, block * n))
        return batches, jax.random.split(k_u, block)

    def work(st_all, kk, k):
        st, ms = _scan_updates(cfg, td3_option(st_all, k), own_inputs(kk, k), identity,
                               seed_axis)
        return st, {name: ms[name].astype(jnp.float32) for name in zero}

    def round_(st_all, x):
        kk, k, on = x
        if seed_axis is None:
            def run(s):
                st, ms = work(s, kk, k)
                return td3_set_option(s, k, st), ms
            return jax.lax.cond(on, run, lambda s: (s, zero), st_all)
        any_on = jax.lax.psum(on.astype(jnp.int32), seed_axis) > 0

        def some(s):
            st, ms = work(s, kk, k)
            st = jax.tree_util.tree_map(lambda a, b: jnp.where(on, a, b), st, td3_option(s, k))
            return td3_set_option(s, k, st), jax.tree_util.tree_map(
                lambda v: jnp.where(on, v, 0.0), ms)
        return jax.lax.cond(any_on, some, lambda s: (s, zero), st_all)

    if not with_global:
        state, ms = jax.lax.scan(round_, state, (jax.random.split(key, num_rounds), option,
                                                 runs))
        return state, _options_metrics(ms, option, runs, K, block)

    # the global option's blocks: td3_updates' keys and minibatches for num_rounds * block steps
    gsteps = num_rounds * block
    placed = gsteps % cfg.policy_delay == 0
    if block == 1:
        gkeys = jax.random.split(global_key, num_rounds)

        def global_inputs(kg):
            ks, ku = jax.random.split(kg)
            return jax.tree_util.tree_map(lambda x: x[None], global_sample_fn(ks, n)), ku[None]
    else:
        gkeys = jax.random.split(jax.random.split(global_key)[0], num_rounds)

        def global_inputs(kg):
            ks, ku = jax.random.split(kg)
            batches = jax.tree_util.tree_map(lambda x: x.reshape((block, n) + x.shape[1:]),
                                             global_sample_fn(ks, block * n))
            return batches, jax.random.split(ku, block)

    def global_alone(carry, kg):
        st_all, st_g = carry
        st_g, mg = _scan_updates(cfg, st_g, global_inputs(kg), identity, seed_axis, placed)
        return (st_all, st_g), (zero, mg)

    def pair(carry, kk, kg, k, on):
        st_all, st_g = carry
        st_o = td3_option(st_all, k)
        both = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), st_o, st_g)
        xs = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), own_inputs(kk, k),
                                    global_inputs(kg))
        both, ms = jax.vmap(lambda s, x: _scan_updates(cfg, s, x, identity, seed_axis, placed)
                            )(both, xs)
        new_o = jax.tree_util.tree_map(lambda a: a[0], both)
        st_g = jax.tree_util.tree_map(lambda a: a[1], both)
        mo = {name: ms[name][0].astype(jnp.float32) for name in zero}
        mg = jax.tree_util.tree_map(lambda a: a[1], ms)
        if seed_axis is not None:
            new_o = jax.tree_util.tree_map(lambda a, b: jnp.where(on, a, b), new_o, st_o)
            mo = jax.tree_util.tree_map(lambda v: jnp.where(on, v, 0.0), mo)
        return (td3_set_option(st_all, k, new_o), st_g), (mo, mg)

    def round_pair(carry, x):
        kk, kg, k, on = x
        pred = on if seed_axis is None else jax.lax.psum(on.astype(jnp.int32), seed_axis) > 0
        return jax.lax.cond(pred, lambda c: pair(c, kk, kg, k, on),
                            lambda c: global_alone(c, kg), carry)

    g = int(global_row)
    (state, st_g), (ms, mg) = jax.lax.scan(
        round_pair, (state, td3_option(state, g)),
        (jax.random.split(key, num_rounds), gkeys, option, runs))
    state = td3_set_option(state, g, st_g)
    metrics = _options_metrics(ms, option, runs, K, block)
    gm = _summarise(jax.tree_util.tree_map(lambda a: a.reshape((gsteps,) + a.shape[2:]), mg))
    metrics.update({f"global_{k}": v for k, v in gm.items()})
    return state, metrics


def _options_metrics(ms, option, runs, K: int, block: int) -> Dict[str, jax.Array]:
    """:func:`td3_updates_options`' metrics from its rounds' per-step metrics ((R, block))."""
    num_rounds = option.shape[0]
    w = jnp.broadcast_to(runs[:, None], (num_rounds, block)).astype(jnp.float32)
    n_steps = jnp.sum(w)
    n_actor = jnp.sum(ms["actor_updated"] * w)
    metrics = {name: jnp.sum(ms[name] * w) / jnp.maximum(n_steps, 1.0)
               for name in ("critic_loss", "q_mean", "target_mean", "reward_mean")}
    metrics["actor_loss"] = jnp.sum(ms["actor_loss"] * w) / jnp.maximum(n_actor, 1.0)
    metrics["actor_updates"] = n_actor
    metrics["option_steps"] = n_steps
    took = jnp.bincount(jnp.where(runs, option, K), length=K + 1)[:K] > 0
    metrics["options_learning"] = jnp.sum(took.astype(jnp.float32))
    return metrics
