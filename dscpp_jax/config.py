"""The run configuration: one frozen, hashable dataclass with the paper's constants as defaults.

`Config` holds every static size and hyperparameter of a run. It is hashable so that it can be a
static argument of `jax.jit`; it is never mutated (use `dataclasses.replace` or `Config.override`).
`Config.validate()` runs before anything is compiled and raises a `ValueError` that says what to
change.

Presets:
- `paper`: the published schedule as far as a batched design allows (B = 1 environment, one TD3
  gradient step per stored transition, 14,000 x 7 MPC, 50 random warm-up episodes, gestation 10,
  buffer 50, timeout 200, 1000-step episodes, 2,000 episodes).
- `fast`: tuned for wall-clock per environment family (many parallel environments, fewer MPC samples
  on the point-mass twins, shorter warm-up); see `preset()` for the exact differences.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import Any

ALGOS = ("mb_dscpp", "mf_dscpp", "dual", "dsc", "td3_her", "mb_flat", "mb_flat_value")
SUBGOALS = ("robust", "dp")
PRESETS = ("paper", "fast")
HIERARCHICAL_ALGOS = ("mb_dscpp", "mf_dscpp", "dual", "dsc")
MODEL_BASED_ALGOS = ("mb_dscpp", "mb_flat", "mb_flat_value")
# Where the `fast` preset turns on the chain's frontier (beyond the paper; dscpp_jax.frontier,
# docs/training.md "The chain's frontier"): the ant mazes and the skill-chaining learners it was
# measured to pay for. With junctions and dead ends (medium, large) the paper's linear chain turns
# away from the start in most seeds; on the medium maze, 10 seeds each: MF-DSC++ 0.77 +- 0.05
# against 0.16 +- 0.16 (5) with the paper's rule, MB-DSC++ 0.72 +- 0.12 with 32 rows, 0.92 +- 0.01
# with 32 rows and the paper's one TD3 step per transition (experiments/results/paper/README.md).
# On four rooms (experiments/results/time_to_result/README.md): MB-DSC++ over 20 seeds
# 0.93 +- 0.01 and every chain at the start, against 0.68 +- 0.10 over 15 with 4 chains that never
# reached it; MF-DSC++ over 10 seeds 0.915 +- 0.014 against 0.87 +- 0.02 (5), at 0.8 after 925
# episodes instead of 1,571; DSC over 10 seeds 0.81 +- 0.09 against 0.46 +- 0.19 (5). The dual
# learner is not measured there and keeps the paper's rule.
FRONTIER_CHAINS = dict(medium=HIERARCHICAL_ALGOS, large=HIERARCHICAL_ALGOS,
                       four_rooms=("mb_dscpp", "mf_dscpp", "dsc"))
FRONTIER_PRESET = dict(frontier_start_prob=0.5, frontier_parent=True, frontier_radius=6.0,
                       frontier_inner_radius=3.0)
# The TD3 of every model-free learner (mf_dscpp, dsc, dual, td3_her) on the ant medium maze, so
# that they keep one TD3 configuration there: HER's `future` strategy at 0.8 and twice the action
# penalty (beyond the paper). With 32 option rows, MF-DSC++ reached 0.91 +- 0.02 over 15 seeds
# (0.87 +- 0.05 over 20), against 0.65 +- 0.08 with `final` at 0.5 and the penalty of 1
# (experiments/results/paper/README.md, sixteenth round).
MEDIUM_MODEL_FREE_TD3 = dict(her_strategy="future", her_relabel_prob=0.8, td3_action_l2=2.0)
# Config fields that were removed, with the value that meant "off" (their default then): a saved
# run that set one of them otherwise cannot be reproduced by this version (`Config.from_saved`).
# Runs written since also record every default beside their config ("config_defaults").
RETIRED_FIELDS: dict[str, Any] = dict(
    td3_upright_weight=0.0, td3_upright_min=0.5, td3_absorb_fallen=False,
    mpc_upright_weight=0.0, mpc_upright_min=0.5, gestation_patience=0,
    frontier_metric="euclidean", frontier_stall=0, svc_bound=0.0, frontier_anchor=0.0,
    warmup_episode_length=0, fall_is_terminal=False, frontier_task_start=False)
# Fields only the host driver reads (the TrainState carries `Config.device_view()`).
HOST_ONLY_DEFAULTS = dict(seed=0, total_env_steps=1, total_episodes=0, eval_every=0,
                          log_every=1, checkpoint_every=0, keep_checkpoints=1, preset="paper")


# Values of fields that a saved config may lack because it predates them: what those runs used.
LEGACY_DEFAULTS = dict(physics="jax")


@dataclass(frozen=True)
class Config:
    """Everything static about a training run (sizes, schedule, hyperparameters)."""

    # --- task and algorithm -------------------------------------------------------------------
    env: str = "point_u_maze"          # envs.make name
    ant_integrator: str = "Euler"      # ant physics: Euler (fast) | RK4 (D4RL's) | implicitfast
    physics: str = "auto"              # ant physics back end: jax (MJX) | warp (MuJoCo Warp) |
                                       # auto (warp on a GPU with warp-lang installed, else jax)
    group_size: int = 1                # seeds trained together in one program (seed groups)
    algo: str = "mb_dscpp"             # one of ALGOS
    subgoal: str = "robust"            # robust | dp
    seed: int = 0

    # --- batching -----------------------------------------------------------------------------
    num_envs: int = 1                  # B parallel environments
    steps_per_iter: int = 1000         # T env steps per train_step (per environment)
    total_env_steps: int = 2_001_000   # stop after this many env steps (all envs together)
    total_episodes: int = 0            # also stop once this many episodes finished (0: no limit)

    # --- episodes and options (paper constants) ----------------------------------------------
    episode_length: int = 1000
    warmup_episodes: int = 50          # uniform-random episodes from the task start
    goal_tolerance: float = 0.6
    gestation: int = 10
    buffer_len: int = 50
    option_timeout: int = 200
    max_options: int = 12              # fixed capacity of the option table (global + goal + links)
    max_pos_traj: int = 100
    max_neg: int = 100
    svm_gamma: float = 0.5
    diverse_starts: bool = True        # training episodes after warm-up start anywhere free
    task_start_prob: float = 0.0       # with diverse starts: the share of training episodes after
                                       # warm-up that start at the task start instead
    # the chain's frontier (beyond the paper; dscpp_jax.frontier, docs/training.md): uncovered free
    # space within frontier_radius of an option's examples, estimated from frontier_candidates
    # diverse-start draws; a row's frontier is open with at least frontier_min_open of them
    frontier_start_prob: float = 0.0   # with diverse starts: the share of training episodes after
                                       # warm-up that start on the frontier of the option that the
                                       # link in gestation targets
    frontier_parent: bool = False      # a new option targets the newest mature option with an
                                       # open frontier; a link in gestation whose target's frontier
                                       # closed (a filled dead end) is re-targeted there
    frontier_radius: float = 5.0
    frontier_inner_radius: float = 0.0  # frontier starts keep at least this far from the target's
                                       # examples (longer links; 0: anywhere on the frontier)
    frontier_candidates: int = 512
    frontier_min_open: int = 4
    eval_prefer_pessimistic: bool = True  # evaluation's policy over options tries pessimistic
                                       # regions first (False: the paper's walk, as in training)

    # --- TD3 + HER ----------------------------------------------------------------------------
    td3_hidden: int = 256
    td3_batch_size: int = 100
    td3_updates_per_step: float = 1.0  # gradient steps per stored env transition
    td3_sample_block: int = 1          # minibatches drawn per replay sampling call (1: one per
                                       # gradient step; > 1: fewer, larger gathers, same math)
    td3_lr: float = -1.0               # < 0: the algorithm's preset (1e-5 model based, 3e-4 free)
    td3_clip_targets: bool = False     # clip TD targets to [-1 / (1 - discount), 0], the range of
                                       # every value under the 0 / -1 reward (not in the original)
    td3_action_l2: float = 0.0         # actor loss + L2 * mean(a^2) (OpenAI Baselines' HER: 1.0;
                                       # 0: off, as in the original)
    td3_dtype: str = "float32"         # matmul operands and activations of TD3's networks:
                                       # float32 or bfloat16 (the hidden layers; the first and
                                       # output layers, parameters, optimiser state, losses
                                       # and targets stay float32; the ant fast preset's
                                       # model-free learners use bfloat16)
    shared_critic: bool = True         # one goal-conditioned TD3 for every option (the paper's
                                       # DSC++); False: one TD3 per option slot, each learning
                                       # from its own transitions (appendix Figure 2; model free)
    discount: float = 0.99
    replay_capacity: int = 1_000_000
    her_strategy: str = "final"        # final | future | none
    her_relabel_prob: float = 0.5
    action_noise: float = 0.1          # Gaussian N(0, 0.1) on the actor's action
    random_action_prob: float = -1.0   # < 0: 0.1 model based, 0.2 model free
    mf_initial_random_prob: float = 0.8  # model free: 0.8 until `mf_random_decay_successes`
    mf_random_decay_successes: int = 3

    # --- dynamics model + MPC -------------------------------------------------------------------
    dyn_hidden: int = 500
    dyn_ensemble: int = 1
    dyn_batch_size: int = 1024
    dyn_lr: float = 1e-3
    dyn_updates_per_step: float = 0.25  # model gradient steps per stored env transition
    dyn_pretrain_steps: int = 2000     # model steps once the warm-up data is in (~50 epochs)
    model_capacity: int = 300_000
    mpc_samples: int = 14_000
    mpc_horizon: int = 7
    mpc_discount: float = 0.95
    mpc_dtype: str = "float32"
    mpc_backend: str = "auto"          # auto: the fused kernel on a GPU with bfloat16, else XLA
    svm_backend: str = "auto"          # auto: the fused SMO kernel on a GPU, else the XLA loop

    # --- in-band evaluation (inside train_step) -------------------------------------------------
    inband_eval_envs: int = 0          # E extra envs that run evaluation episodes from the task
                                       # start in the same scan as the training envs: the
                                       # deterministic evaluation policy, nothing written to
                                       # learning state (0: off; metrics inband/*)
    inband_eval_window: int = 0        # inband/success_rate over the last K finished in-band
                                       # episodes (0: K = inband_eval_envs)
    inband_eval_batched: bool = True   # step the in-band envs in one physics batch with the
                                       # training envs (B + E); False: a second physics step.
                                       # MJX (JAX) ant physics may round a B + E batch
                                       # differently, so training then matches a run without
                                       # in-band envs only to rounding; False keeps it bitwise.
                                       # Point mass and MuJoCo Warp: exact either way

    # --- evaluation, logging, checkpoints (host side) -----------------------------------------
    eval_every: int = 10               # train_step calls between evaluations (0: never)
    eval_episodes: int = 4
    log_every: int = 1
    checkpoint_every: int = 20         # train_step calls between checkpoints (0: only at exit)
    keep_checkpoints: int = 2
    preset: str = "paper"

    # ------------------------------------------------------------------------------------------
    @property
    def hierarchical(self) -> bool:
        return self.algo in HIERARCHICAL_ALGOS

    @property
    def model_based(self) -> bool:
        return self.algo in MODEL_BASED_ALGOS

    @property
    def uses_value_in_mpc(self) -> bool:
        return self.algo in ("mb_dscpp", "mb_flat_value")

    @property
    def classifier_variant(self) -> str:
        return "single" if self.algo == "dsc" else "dual"

    @property
    def steps_per_iteration_total(self) -> int:
        return self.num_envs * self.steps_per_iter

    @property
    def td3_updates(self) -> int:
        """TD3 gradient steps per train_step."""
        return max(1, int(round(self.td3_updates_per_step * self.steps_per_iteration_total)))

    @property
    def dyn_updates(self) -> int:
        """Dynamics-model gradient steps per train_step (model-based algorithms only)."""
        if not self.model_based:
            return 0
        return max(1, int(round(self.dyn_updates_per_step * self.steps_per_iteration_total)))

    @property
    def effective_random_prob(self) -> float:
        if self.random_action_prob >= 0:
            return self.random_action_prob
        return 0.1 if self.model_based else 0.2

    @property
    def effective_td3_lr(self) -> float:
        if self.td3_lr > 0:
            return self.td3_lr
        return 1e-5 if self.model_based else 3e-4

    @property
    def inband_window(self) -> int:
        """K: finished in-band episodes that `inband/success_rate` averages over."""
        return self.inband_eval_window if self.inband_eval_window > 0 else self.inband_eval_envs

    @property
    def num_iterations(self) -> int:
        return -(-self.total_env_steps // self.steps_per_iteration_total)

    @property
    def frontier_on(self) -> bool:
        """Whether the skill chain uses the chain's frontier (frontier starts or parents)."""
        return self.hierarchical and (self.frontier_start_prob > 0 or self.frontier_parent)

    def inert_fields(self) -> frozenset:
        """Fields this config's other settings leave without effect (comparing two configs, a
        difference in them changes nothing): the chain's frontier's parameters where the frontier
        is off, and the frontier starts' inner radius where only frontier parents are on."""
        if not self.frontier_on:
            return frozenset({"frontier_radius", "frontier_inner_radius", "frontier_candidates",
                              "frontier_min_open"})
        return frozenset() if self.frontier_start_prob > 0 else frozenset({"frontier_inner_radius"})

    # ------------------------------------------------------------------------------------------
    def override(self, **kw: Any) -> "Config":
        """A copy with some fields replaced (unknown names raise a ValueError)."""
        names = {f.name for f in dataclasses.fields(self)}
        bad = sorted(set(kw) - names)
        if bad:
            raise ValueError(f"unknown config field(s) {bad}; valid fields: {sorted(names)}")
        return dataclasses.replace(self, **kw)

    def device_view(self) -> "Config":
        """The fields that shape the jitted computation; host-only fields (seed, schedule length,
        logging/checkpoint cadence, preset name) reset, so changing them never recompiles."""
        return dataclasses.replace(self, **HOST_ONLY_DEFAULTS)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict) -> "Config":
        names = {f.name for f in dataclasses.fields(cls)}
        d = {**LEGACY_DEFAULTS, **d}
        return cls(**{k: v for k, v in d.items() if k in names})

    @classmethod
    def from_saved(cls, d: Any, defaults: Any = None, source: str = "this run") -> "Config":
        """The Config of a saved run (config.json's "config"), checked against this version.

        Fields the run lacks (added since) take their defaults, which is what it used. Fields this
        version no longer has are ignored when they hold the value that meant "off" (the default
        recorded beside the run, `defaults`, else `RETIRED_FIELDS`); any other value raises a
        ValueError naming them, since the run's results depend on behaviour that is gone."""
        if not isinstance(d, dict):
            raise ValueError(f"{source}: config.json's \"config\" is not a mapping of Config fields")
        names = {f.name for f in dataclasses.fields(cls)}
        off = {**RETIRED_FIELDS, **(defaults if isinstance(defaults, dict) else {})}
        _missing = object()
        gone = {k: v for k, v in d.items() if k not in names and off.get(k, _missing) != v}
        if gone:
            said = ", ".join(f"{k}={v!r}" + (f" (off: {off[k]!r})" if k in off else "")
                             for k, v in sorted(gone.items()))
            raise ValueError(
                f"{source} was made by another (older) version of dscpp_jax: it sets {said}, "
                f"which this version no longer has, so it cannot continue or evaluate that run as "
                f"it was trained. Use the version that made it (its commit is config.json's "
                f"versions.dscpp_jax_git) or train a new run")
        try:
            return cls.from_dict(d)
        except TypeError as e:
            raise ValueError(f"{source}: config.json's \"config\" does not fit this version's "
                             f"Config ({e})") from None

    def validate(self) -> "Config":
        """Raise a ValueError naming the fix for any impossible setting; return self."""
        def need(cond: bool, msg: str) -> None:
            if not cond:
                raise ValueError(f"invalid config: {msg}")

        need(self.algo in ALGOS, f"algo={self.algo!r}; choose one of {ALGOS}")
        need(self.subgoal in SUBGOALS, f"subgoal={self.subgoal!r}; choose one of {SUBGOALS}")
        need(self.preset in PRESETS, f"preset={self.preset!r}; choose one of {PRESETS}")
        need(self.her_strategy in ("final", "future", "none"),
             f"her_strategy={self.her_strategy!r}; choose final, future or none")
        for name in ("num_envs", "steps_per_iter", "episode_length", "option_timeout", "buffer_len",
                     "gestation", "td3_batch_size", "dyn_batch_size", "mpc_samples", "mpc_horizon",
                     "eval_episodes", "max_pos_traj", "max_neg", "td3_hidden", "dyn_hidden",
                     "dyn_ensemble", "total_env_steps"):
            need(int(getattr(self, name)) >= 1, f"{name}={getattr(self, name)} must be >= 1")
        need(self.max_options >= 3, f"max_options={self.max_options} must be >= 3 (global, goal "
             "and at least one chain link)")
        need(self.warmup_episodes >= 0, "warmup_episodes must be >= 0")
        for name in ("eval_every", "checkpoint_every"):
            need(int(getattr(self, name)) >= 0,
                 f"{name}={getattr(self, name)} must be >= 0 (train_step calls between them; "
                 f"0: {'never' if name == 'eval_every' else 'only at exit'})")
        need(self.log_every >= 1, f"log_every={self.log_every} must be >= 1")
        need(self.keep_checkpoints >= 1, f"keep_checkpoints={self.keep_checkpoints} must be >= 1")
        need(self.seed >= 0, f"seed={self.seed} must be >= 0 (seeds are non-negative integers, "
             "as --seeds takes them)")
        need(self.total_episodes >= 0, "total_episodes must be >= 0 (0: no episode limit)")
        need(self.goal_tolerance > 0, "goal_tolerance must be > 0")
        need(0.0 < self.discount <= 1.0, "discount must be in (0, 1]")
        need(0.0 < self.mpc_discount <= 1.0, "mpc_discount must be in (0, 1]")
        need(not self.td3_clip_targets or self.discount < 1.0,
             "td3_clip_targets needs discount < 1 (with discount 1 the values have no lower "
             "bound); lower discount or set td3_clip_targets=false")
        need(0.0 <= self.her_relabel_prob <= 1.0, "her_relabel_prob must be in [0, 1]")
        need(self.random_action_prob <= 1.0, "random_action_prob must be <= 1")
        need(self.td3_updates_per_step >= 0 and self.dyn_updates_per_step >= 0,
             "updates_per_step values must be >= 0")
        need(self.td3_sample_block >= 1,
             f"td3_sample_block must be >= 1 (1: one replay sample per gradient step), got "
             f"{self.td3_sample_block}")
        need(self.mpc_dtype in ("float32", "bfloat16"), "mpc_dtype must be float32 or bfloat16")
        need(self.td3_action_l2 >= 0, "td3_action_l2 must be >= 0 (0: off)")
        need(self.td3_dtype in ("float32", "bfloat16"), "td3_dtype must be float32 or bfloat16")
        need(self.physics in ("auto", "jax", "warp"),
             f"physics={self.physics!r}; choose auto, jax (MJX) or warp (MuJoCo Warp)")
        need(self.group_size >= 1, f"group_size={self.group_size} must be >= 1")
        need(self.ant_integrator in ("Euler", "RK4", "implicitfast"),
             f"ant_integrator must be Euler, RK4 or implicitfast, got {self.ant_integrator!r}")
        for name in ("mpc_backend", "svm_backend"):
            need(getattr(self, name) in ("auto", "xla", "pallas"),
                 f"{name}={getattr(self, name)!r}; choose auto, xla or pallas")
        need(self.mpc_backend != "pallas" or self.mpc_dtype == "bfloat16",
             "mpc_backend=pallas computes in bfloat16: also set mpc_dtype=bfloat16 (or use "
             "mpc_backend=xla)")
        per_env = self.replay_capacity // self.num_envs
        need(per_env >= max(2, self.steps_per_iter),
             f"replay_capacity={self.replay_capacity} gives {per_env} steps per environment for "
             f"num_envs={self.num_envs}; raise replay_capacity to at least "
             f"{self.num_envs * max(2, self.steps_per_iter)}")
        need(per_env >= self.option_timeout + 1,
             f"replay_capacity per environment ({per_env}) must exceed option_timeout="
             f"{self.option_timeout} so HER can see whole option segments; raise replay_capacity")
        if self.model_based:
            mper = self.model_capacity // self.num_envs
            need(mper >= max(2, self.steps_per_iter),
                 f"model_capacity={self.model_capacity} too small for num_envs={self.num_envs} and "
                 f"steps_per_iter={self.steps_per_iter}; raise it to at least "
                 f"{self.num_envs * max(2, self.steps_per_iter)}")
        need(self.inband_eval_envs >= 0,
             f"inband_eval_envs={self.inband_eval_envs} must be >= 0 (0: no in-band evaluation; "
             f"e.g. 16 runs 16 evaluation episodes from the task start inside each train_step)")
        need(self.inband_eval_window >= 0,
             f"inband_eval_window={self.inband_eval_window} must be >= 0 (0: the last "
             f"inband_eval_envs finished in-band episodes)")
        need(self.buffer_len < self.option_timeout + 1,
             "buffer_len must be <= option_timeout")
        need(0.0 <= float(self.task_start_prob) <= 1.0,
             f"task_start_prob={self.task_start_prob} must be in [0, 1] (the share of training "
             f"episodes that start at the task start; 0: all diverse starts)")
        need(0.0 <= float(self.frontier_start_prob) <= 1.0
             and float(self.task_start_prob) + float(self.frontier_start_prob) <= 1.0,
             f"frontier_start_prob={self.frontier_start_prob} must be in [0, 1] and, with "
             f"task_start_prob={self.task_start_prob}, sum to at most 1 (the shares of training "
             f"episodes that start at the task start and on the chain's frontier)")
        need(self.frontier_start_prob == 0 or self.diverse_starts,
             "frontier_start_prob > 0 draws some of the diverse starts on the chain's frontier: "
             "it needs diverse_starts=true")
        need(self.frontier_start_prob == 0 and not self.frontier_parent or self.hierarchical,
             f"frontier_start_prob and frontier_parent act on the skill chain: algo={self.algo!r} "
             f"has none; use one of {HIERARCHICAL_ALGOS} or leave them off")
        need(0 <= self.frontier_inner_radius < self.frontier_radius,
             f"frontier_inner_radius={self.frontier_inner_radius} and frontier_radius="
             f"{self.frontier_radius}: need 0 <= frontier_inner_radius < frontier_radius")
        need(self.frontier_candidates >= 1 and self.frontier_min_open >= 1,
             f"frontier_candidates={self.frontier_candidates} and frontier_min_open="
             f"{self.frontier_min_open} must be >= 1")
        need(isinstance(self.shared_critic, bool),
             f"shared_critic={self.shared_critic!r} must be True or False")
        need(self.shared_critic or not self.model_based,
             f"shared_critic=False (one TD3 per option) is implemented for the model-free "
             f"algorithms only ({', '.join(a for a in ALGOS if a not in MODEL_BASED_ALGOS)}): "
             f"algo={self.algo!r} plans with MPC, whose value term uses one critic for all "
             f"envs; set shared_critic=True or use algo='mf_dscpp'")
        return self


# ------------------------------------------------------------------------------------------------
# Presets
# ------------------------------------------------------------------------------------------------
def _is_point(env: str) -> bool:
    return env.startswith("point_")


def preset(name: str = "fast", env: str = "point_u_maze", algo: str = "mb_dscpp",
           **overrides: Any) -> Config:
    """A named preset for an env and algorithm, with field overrides applied last.

    paper: the published schedule as far as a batched design allows: B = 1 environment, T = 1000
      steps per iteration, one TD3 step per transition, 14,000 x 7 MPC, 50 warm-up episodes, 2,001
      episodes, and on the ant D4RL's RK4 integrator. Learning and classifier refits happen once
      per T steps rather than after every option rollout. Slow by design (hours on the ant).
    fast, point-mass twins (a laptop CPU, a few minutes): 16 envs x 100 steps, 500-step episodes,
      8 warm-up episodes, 128 x 7 MPC with a 2 x 64 model, a 2 x 64 actor/critic at 3e-4 with 0.25
      TD3 steps per transition for both variants, gestation 5 (the paper's U-maze value), at most
      8 options, 100k env steps.
    fast, ant mazes (one GPU, 2,001 episodes in about 6-14 minutes): 128 envs x 50 steps,
      1000-step episodes, 4,096 x 7 MPC in bfloat16 (the fused kernel on a GPU; 2,048 x 7 on the
      U-maze, as good there and 1.6x the model-based seed group's speed), 0.1 model steps per
      transition; TD3 at 0.25 steps per transition, batch 256 and 1e-4 (model based) or the
      paper's 1 step per transition at batch 512 and 3e-4 with an L2 action penalty of 1 (model
      free; bf16 in TD3's hidden layers, as fast in a seed group and as good on the ant, float32
      for the model-based learners); TD targets clipped to [-1 / (1 - discount), 0] (keeps the model-based critic stable);
      32 minibatches per replay sampling call (speed); RK4 (fewer tip-overs); gestation 5 (10 on
      four rooms, appendix Table 4); up to 24 options; evaluation inside training (32 in-band
      envs, success every iteration) and 100 episodes at the end instead of periodic
      evaluations; stops at 2,001 episodes (or 4M env steps). On the mazes with junctions and
      dead ends (medium, large) the skill chains also use the chain's frontier (beyond the paper:
      half the training episodes start on it, and a chain that has filled a dead end branches
      back; `FRONTIER_PRESET`), and so do MB-DSC++, MF-DSC++ and DSC on four rooms
      (`FRONTIER_CHAINS`). On the medium maze they have 32 option rows, MB-DSC++ runs the
      paper's 1 TD3 step per transition (about 18 minutes for 5 seeds on one H200), and every
      model-free learner HER's `future` strategy at 0.8 with an action penalty of 2
      (`MEDIUM_MODEL_FREE_TD3`).

    Why each setting, with the measurements: docs/training.md ("Presets") and
    experiments/results/train_ant/README.md.
    """
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {PRESETS}")
    base: dict[str, Any] = dict(env=env, algo=algo, preset=name)
    if name == "paper":
        base.update(num_envs=1, steps_per_iter=1000, total_env_steps=2_001_000,
                    total_episodes=2001,
                    eval_every=10, eval_episodes=1, checkpoint_every=50)
        if not _is_point(env):
            base.update(ant_integrator="RK4")
    elif _is_point(env):
        base.update(
            num_envs=16, steps_per_iter=100, total_env_steps=100_000,
            episode_length=500, warmup_episodes=8, gestation=5,
            max_options=8, max_pos_traj=50, max_neg=50,
            td3_updates_per_step=0.25, td3_batch_size=256, td3_hidden=64, td3_lr=3e-4,
            replay_capacity=200_000, model_capacity=100_000,
            dyn_hidden=64, dyn_updates_per_step=0.02, dyn_pretrain_steps=300,
            dyn_batch_size=256, mpc_samples=128,
            eval_every=5, eval_episodes=8, checkpoint_every=10,
        )
    else:
        base.update(
            num_envs=128, steps_per_iter=50, total_env_steps=4_000_000, total_episodes=2001,
            gestation=10 if env == "four_rooms" else 5,
            td3_updates_per_step=0.25 if algo in MODEL_BASED_ALGOS else 1.0,
            td3_batch_size=256 if algo in MODEL_BASED_ALGOS else 512,
            td3_lr=1e-4 if algo in MODEL_BASED_ALGOS else -1.0,
            replay_capacity=1_000_000, model_capacity=300_000,
            dyn_updates_per_step=0.1, dyn_pretrain_steps=2000,
            mpc_samples=2048 if env == "u_maze" else 4096,
            mpc_dtype="bfloat16", max_options=24, td3_clip_targets=True,
            ant_integrator="RK4", td3_sample_block=32,
            td3_action_l2=0.0 if algo in MODEL_BASED_ALGOS else 1.0,
            td3_dtype="float32" if algo in MODEL_BASED_ALGOS else "bfloat16",
            inband_eval_envs=32, eval_every=0, eval_episodes=100, checkpoint_every=25,
        )
        if algo in FRONTIER_CHAINS.get(env, ()) and overrides.get(
                "diverse_starts", True):
            base.update(FRONTIER_PRESET)
            if env == "medium":
                base.update(max_options=32)
            if env == "medium" and algo == "mb_dscpp":
                base.update(td3_updates_per_step=1.0)
        if env == "medium" and algo not in MODEL_BASED_ALGOS:
            base.update(MEDIUM_MODEL_FREE_TD3)
    base.update(overrides)
    return Config(**base)


def parse_value(field_name: str, text: str) -> Any:
    """Convert a command-line string to the type of Config field `field_name`."""
    types = {f.name: f.type for f in dataclasses.fields(Config)}
    if field_name not in types:
        raise ValueError(f"unknown config field {field_name!r}; valid: {sorted(types)}")
    t = types[field_name]
    t = t if isinstance(t, str) else getattr(t, "__name__", str(t))
    if t == "bool":
        if text.lower() in ("1", "true", "yes", "on"):
            return True
        if text.lower() in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"--set {field_name}={text!r}: {field_name} is true or false, e.g. "
                         f"--set {field_name}=true")
    try:
        if t == "int":
            v = float(text) if "e" in text.lower() else int(text)
            if v != int(v):
                raise ValueError(text)
            return int(v)
        if t == "float":
            return float(text)
    except ValueError:
        example = getattr(Config(), field_name)
        raise ValueError(f"--set {field_name}={text!r}: {field_name} is {_TYPE_NAMES[t]}, e.g. "
                         f"--set {field_name}={example}") from None
    return text


_TYPE_NAMES = {"int": "an integer", "float": "a number"}
