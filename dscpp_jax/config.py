"""The run configuration: one frozen, hashable dataclass of component sections with the paper's
constants as defaults, and the presets, a table of field overrides per environment family and
learner.

`Config` holds every static size and hyperparameter of a run: what the run is (env, algo, subgoal,
preset) and one frozen section per component (`task`, `run`, `td3`, `dynamics`, `mpc`, `chain`,
`frontier`, `eval`; e.g. `cfg.td3.lr`, `cfg.mpc.samples`), each field documented where it is
declared. Every field also has a flat name (`td3_lr`, `mpc_samples`; the table `FLAT_NAMES`),
which `--set`, `preset`, `Config(...)` and `Config.override` take as they take `section.field`.
It is hashable so that it can be a static argument of `jax.jit`; it is never mutated
(use `Config.override`). Constructing one checks every field's type;
`Config.override` and `Config.validate()` also check the value of each field with a fixed set
of values (`CHOICES`), and `validate()`, which runs before anything is compiled, checks the
settings against each other. Each raises a `ValueError` that names the field and says
what to change. (A config loaded from a saved run is only type-checked, so that a run made with a
value this version no longer has can still be read.)

Presets (`preset(name, env, algo, **overrides)`, the table `PRESET_TABLE`):
- `paper`: the published schedule as far as a batched design allows: one environment, one TD3
  gradient step per stored transition, the paper's MPC, warm-up, gestation, buffer, timeout,
  episode length and number of episodes.
- `fast`: tuned for wall-clock per environment family: many parallel environments, a smaller
  model on the point-mass twins, in-band evaluation on the ant mazes, and on the ant mazes with
  junctions and dead ends the chain's frontier for DSC++ (`FRONTIER_TABLE`). The paper's
  baselines (`PAPER_BASELINES`) get nothing beyond the paper in any preset;
  `paper_rule_overrides` turns DSC++'s extras off.

Why each preset value was chosen, with the study behind it: docs/presets.md.
"""
from __future__ import annotations

import dataclasses
import difflib
import json
import numbers
from dataclasses import dataclass
from typing import Any

ALGOS = ("mb_dscpp", "mf_dscpp", "dual", "dsc", "td3_her", "mb_flat", "mb_flat_value")
SUBGOALS = ("robust", "dp")
PRESETS = ("paper", "fast")
HIERARCHICAL_ALGOS = ("mb_dscpp", "mf_dscpp", "dual", "dsc")
MODEL_BASED_ALGOS = ("mb_dscpp", "mb_flat", "mb_flat_value")
MODEL_FREE_ALGOS = tuple(a for a in ALGOS if a not in MODEL_BASED_ALGOS)
# The environments `envs.make` builds by name: the ant mazes and their point-mass twins.
MAZES = ("u_maze", "medium", "large", "four_rooms", "ant_reacher")
ENV_FAMILIES = dict(ant=MAZES, point=tuple("point_" + m for m in MAZES))
ENV_NAMES = ENV_FAMILIES["ant"] + ENV_FAMILIES["point"]
# Learner classes a preset entry can be keyed by (besides "*" and a single algorithm).
LEARNER_CLASSES = dict(model_based=MODEL_BASED_ALGOS, model_free=MODEL_FREE_ALGOS)
# The values a string field can take (the others, env included, are free strings; `envs.make`
# checks the env name).
DTYPES = ("float32", "bfloat16")
KERNEL_BACKENDS = ("auto", "xla", "pallas")
CHOICES: dict[str, tuple] = dict(
    algo=ALGOS, subgoal=SUBGOALS, preset=PRESETS, her_strategy=("final", "future", "none"),
    physics=("auto", "jax", "warp"), ant_integrator=("Euler", "RK4", "implicitfast"),
    td3_dtype=DTYPES, mpc_dtype=DTYPES, mpc_backend=KERNEL_BACKENDS, svm_backend=KERNEL_BACKENDS,
    option_init=("copy_global", "random"))

# The paper's baselines (Figure 5's ladder below DSC++): every preset gives them the paper's
# settings and nothing beyond (no frontier, no medium-maze TD3, no action penalty).
PAPER_BASELINES = ("dsc", "dual")
DSCPP_ALGOS = ("mb_dscpp", "mf_dscpp")
# The ant mazes and learners whose skill chains use the chain's frontier in the `fast` preset
# (beyond the paper; dscpp_jax.frontier): DSC++'s, not the baselines'. `FRONTIER_TABLE` holds
# what it sets.
FRONTIER_CHAINS = dict(medium=DSCPP_ALGOS, large=DSCPP_ALGOS, four_rooms=DSCPP_ALGOS)
FRONTIER_PRESET = dict(frontier_start_prob=0.5, frontier_parent=True, frontier_radius=6.0,
                       frontier_inner_radius=3.0)
# The TD3 of MF-DSC++ and TD3+HER on the ant medium maze in the `fast` preset (beyond the paper):
# HER's `future` strategy and a larger action penalty.
MEDIUM_MODEL_FREE_TD3 = dict(her_strategy="future", her_relabel_prob=0.8, td3_action_l2=2.0)
# Preset entries beyond the paper besides FRONTIER_TABLE (`preset_fields(beyond_paper=False)`
# leaves them out).
BEYOND_PAPER_ENTRIES = (MEDIUM_MODEL_FREE_TD3,)
# Config fields that were removed, with the value that meant "off" (their default then): a saved
# run that set one of them otherwise cannot be reproduced by this version (`Config.from_saved`).
# Runs written since also record every default beside their config ("config_defaults").
RETIRED_FIELDS: dict[str, Any] = dict(
    td3_upright_weight=0.0, td3_upright_min=0.5, td3_absorb_fallen=False,
    mpc_upright_weight=0.0, mpc_upright_min=0.5, gestation_patience=0,
    frontier_metric="euclidean", frontier_stall=0, svc_bound=0.0, frontier_anchor=0.0,
    warmup_episode_length=0, fall_is_terminal=False, frontier_task_start=False, log_every=1)
# Fields only the host driver reads (the TrainState carries `Config.device_view()`).
HOST_ONLY_DEFAULTS = dict(seed=0, total_env_steps=1, total_episodes=0, eval_every=0,
                          checkpoint_every=0, keep_checkpoints=1, preset="paper")


# Values of fields that a saved config may lack because it predates them: what those runs used.
LEGACY_DEFAULTS = dict(physics="jax")



class Section:
    """Base of the config's sections: constructing one type-checks its fields."""

    def __post_init__(self):
        _check_section(self)


@dataclass(frozen=True)
class TaskSection(Section):
    """The environment's physics and episodes: their length, the warm-up, the goal
    tolerance and where training episodes start."""

    ant_integrator: str = "Euler"
    """MuJoCo integrator of the ant: Euler (fast), RK4 (D4RL's) or implicitfast"""
    physics: str = "auto"
    """ant physics back end: jax (MJX), warp (MuJoCo Warp) or auto (warp on a GPU with warp-lang
    installed, else jax)"""
    episode_length: int = 1000
    """env steps per episode"""
    warmup_episodes: int = 50
    """uniform-random episodes from the task start before learning"""
    goal_tolerance: float = 0.6
    """radius of the task's goal region and of a subgoal's region (distance)"""
    diverse_starts: bool = True
    """training episodes after warm-up start anywhere free (False: at the task start)"""
    start_prob: float = 0.0
    """with diverse starts: the share of training episodes after warm-up that start at the task
    start instead (a probability)"""


@dataclass(frozen=True)
class RunSection(Section):
    """The run's seed, batching, schedule and checkpoints."""

    seed: int = 0
    """the run's random seed (>= 0)"""
    group_size: int = 1
    """seeds trained together in one program (a seed group)"""
    num_envs: int = 1
    """B: parallel training environments"""
    steps_per_iter: int = 1000
    """T: env steps per environment in one train_step call"""
    total_env_steps: int = 2_001_000
    """stop after this many env steps (all environments together)"""
    total_episodes: int = 0
    """also stop once this many episodes have finished (0: no limit)"""
    checkpoint_every: int = 20
    """train_step calls between checkpoints (0: only at exit)"""
    keep_checkpoints: int = 2
    """checkpoints kept in the run directory (the newest)"""


@dataclass(frozen=True)
class TD3Section(Section):
    """TD3 + HER (the option policies and the value function V(s | g)), their replay buffer
    and exploration."""

    hidden: int = 256
    """width of the hidden layers of TD3's actor and critics (units)"""
    batch_size: int = 100
    """transitions per TD3 minibatch"""
    updates_per_step: float = 1.0
    """TD3 gradient steps per stored env transition"""
    sample_block: int = 1
    """minibatches drawn per replay sampling call (1: one per gradient step; > 1: fewer, larger
    gathers, same math)"""
    lr: float = -1.0
    """Adam learning rate of TD3 (< 0: the learner's own, 1e-5 model based, 3e-4 model free)"""
    clip_targets: bool = False
    """clip TD targets to [-1 / (1 - discount), 0], the range of every value under the 0 / -1
    reward (not in the original)"""
    action_l2: float = 0.0
    """weight of the actor's action penalty: actor loss + td3_action_l2 * mean(a^2) (OpenAI
    Baselines' HER: 1; 0: off, as in the original)"""
    dtype: str = "float32"
    """matmul operands and activations of TD3's hidden layers: float32 or bfloat16 (the first and
    output layers, parameters, optimiser state, losses and targets stay float32)"""
    shared_critic: bool = True
    """goal-conditioned option policies (`option_policies`): one TD3 for every option (the
    paper's DSC++); False: one TD3 per option slot, each learning from its own transitions while
    the global option's learns from all (appendix Figure 2; model free). dsc and dual always
    learn one TD3 per option."""
    discount: float = 0.99
    """TD3's discount per env step"""
    replay_capacity: int = 1_000_000
    """replay buffer size in transitions (all environments together)"""
    her_strategy: str = "final"
    """hindsight relabelling: final, future or none"""
    her_relabel_prob: float = 0.5
    """probability that a sampled transition's goal is relabelled"""
    action_noise: float = 0.1
    """standard deviation of the Gaussian noise on the actor's action (action units)"""
    random_action_prob: float = -1.0
    """probability of a uniform-random action when exploring (< 0: 0.1 model based, 0.2 model
    free)"""
    mf_initial_random_prob: float = 0.8
    """model free: the random-action probability until mf_random_decay_successes"""
    mf_random_decay_successes: int = 3
    """model free: successes after which random_action_prob replaces mf_initial_random_prob"""

    def effective_lr(self, model_based: bool) -> float:
        """The learning rate in effect: `lr`, or where it is < 0 the learner's own."""
        return self.lr if self.lr > 0 else (1e-5 if model_based else 3e-4)


@dataclass(frozen=True)
class DynamicsSection(Section):
    """The learned dynamics model f_xi of the model-based algorithms."""

    hidden: int = 500
    """width of the dynamics model's hidden layers (units)"""
    ensemble: int = 1
    """members of the dynamics model's ensemble"""
    batch_size: int = 1024
    """transitions per dynamics-model minibatch"""
    lr: float = 1e-3
    """Adam learning rate of the dynamics model"""
    updates_per_step: float = 0.25
    """dynamics-model gradient steps per stored env transition"""
    pretrain_steps: int = 2000
    """dynamics-model gradient steps once the warm-up data is in"""
    capacity: int = 300_000
    """the dynamics model's transition buffer size (all environments together)"""


@dataclass(frozen=True)
class MPCSection(Section):
    """Random-shooting MPC over the learned model (eq. 2; eq. 1 without the value term)."""

    samples: int = 14_000
    """action sequences MPC samples per decision"""
    horizon: int = 7
    """env steps each sampled action sequence looks ahead"""
    discount: float = 0.95
    """discount per step of MPC's return (also of the DP subgoals' value table)"""
    dtype: str = "float32"
    """precision of MPC's rollouts: float32 or bfloat16"""
    backend: str = "auto"
    """MPC's kernel: xla, pallas (the fused kernel; bfloat16) or auto (pallas on a GPU with
    bfloat16, else xla)"""


@dataclass(frozen=True)
class ChainSection(Section):
    """The skill chain: gestation, option executions, the example rings, the initiation
    classifiers and how new options start."""

    gestation: int = 10
    """successful executions before a new option is mature"""
    buffer_len: int = 50
    """positions kept after the start state of a successful execution (env steps)"""
    option_timeout: int = 200
    """env steps before an option's execution counts as a failure"""
    max_options: int = 12
    """capacity of the option table: the global option, the goal option and the chain's links"""
    max_pos_traj: int = 100
    """successful trajectories kept per option (a ring)"""
    max_neg: int = 100
    """failed start states kept per option (a ring)"""
    svm_gamma: float = 0.5
    """RBF kernel coefficient of the initiation classifiers (1 / distance squared)"""
    svm_backend: str = "auto"
    """the classifiers' SMO solver: xla (a loop), pallas (the fused kernel) or auto (pallas on a
    GPU, else xla)"""
    option_init: str = "copy_global"
    """one TD3 per option (`option_policies`): how a new option's networks start: copy_global (a
    copy of the global option's networks, target networks included, fresh optimiser state, at
    the option's creation) or random"""
    global_option_timeout: int = 0
    """env steps the global option runs before the policy over options chooses again (0: the
    algorithm's: 1 for dsc and dual, as the authors' baseline; option_timeout otherwise)"""
    initiation_period: int = -1
    """successes beyond gestation the newest mature option needs before the chain creates its
    child (< 0: the algorithm's: 2 for dsc and dual, as DSC's initiation period; 0 otherwise)"""


@dataclass(frozen=True)
class FrontierSection(Section):
    """The chain's frontier (beyond the paper; dscpp_jax.frontier): uncovered free space
    within `radius` of an option's examples, estimated from `candidates` diverse-start draws; a
    row's frontier is open with at least `min_open` of them."""

    start_prob: float = 0.0
    """with diverse starts: the share of training episodes after warm-up that start on the
    frontier of the option that the link in gestation targets (a probability; 0: off)"""
    parent: bool = False
    """a new option targets the newest mature option with an open frontier; a link in gestation
    whose target's frontier closed (a filled dead end) is re-targeted there"""
    radius: float = 5.0
    """how far the frontier reaches from an option's examples (distance)"""
    inner_radius: float = 0.0
    """frontier starts keep at least this far from the target's examples (distance; 0: anywhere
    on the frontier)"""
    candidates: int = 512
    """diverse-start draws the frontier is estimated from"""
    min_open: int = 4
    """draws on a row's frontier for it to count as open"""
    goal_starts: bool = False
    """frontier starts for the goal option too: while it is in gestation (no mature option has
    a frontier yet) they are drawn from free space within `radius` of the task goal and at least
    `inner_radius` from it (False: frontier starts begin once the goal option is mature)"""


@dataclass(frozen=True)
class EvalSection(Section):
    """Evaluation: separate episodes between train_step calls (host side) and in-band
    episodes inside train_step."""

    every: int = 10
    """train_step calls between evaluations (0: never)"""
    episodes: int = 4
    """episodes per evaluation"""
    prefer_pessimistic: bool = True
    """evaluation's policy over options tries pessimistic regions first (False: the paper's walk,
    as in training)"""
    inband_envs: int = 0
    """E: extra environments that run evaluation episodes from the task start in the same scan as
    the training environments, with the deterministic evaluation policy and nothing written to
    learning state (0: off; metrics inband/*)"""
    inband_window: int = 0
    """inband/success_rate averages the last K finished in-band episodes (0: K =
    inband_eval_envs)"""
    inband_batched: bool = True
    """step the in-band environments in one physics batch with the training environments
    (B + E); False: a second physics step. MJX (JAX) ant physics may round a B + E batch
    differently, so training then matches a run without in-band environments only to rounding;
    False keeps it bitwise. Point mass and MuJoCo Warp: exact either way"""


SECTIONS: dict[str, type] = dict(task=TaskSection, run=RunSection, td3=TD3Section,
                                 dynamics=DynamicsSection, mpc=MPCSection, chain=ChainSection,
                                 frontier=FrontierSection, eval=EvalSection)
"""Config's sections: attribute name -> section class."""
TOP_FIELDS = ("env", "algo", "subgoal", "preset")
"""Config's fields outside the sections: what the run is (env, learner, subgoals, preset)."""

# The one table of input names: every field's flat name (the name it had before the sections,
# still accepted by `--set`, `preset`, `Config(...)` and `Config.override`, and used in error
# messages and saved flat configs) -> (section, field); None for the fields outside the sections.
# `section.field` (e.g. `td3.lr`) is accepted wherever a flat name is. In the order of the flat
# fields before the sections (`Config.flat`'s order).
FLAT_NAMES: dict[str, tuple[str | None, str]] = {
    "env": (None, "env"), "ant_integrator": ("task", "ant_integrator"),
    "physics": ("task", "physics"), "group_size": ("run", "group_size"), "algo": (None, "algo"),
    "subgoal": (None, "subgoal"), "seed": ("run", "seed"), "num_envs": ("run", "num_envs"),
    "steps_per_iter": ("run", "steps_per_iter"), "total_env_steps": ("run", "total_env_steps"),
    "total_episodes": ("run", "total_episodes"), "episode_length": ("task", "episode_length"),
    "warmup_episodes": ("task", "warmup_episodes"), "goal_tolerance": ("task", "goal_tolerance"),
    "gestation": ("chain", "gestation"), "buffer_len": ("chain", "buffer_len"),
    "option_timeout": ("chain", "option_timeout"), "max_options": ("chain", "max_options"),
    "max_pos_traj": ("chain", "max_pos_traj"), "max_neg": ("chain", "max_neg"),
    "svm_gamma": ("chain", "svm_gamma"), "diverse_starts": ("task", "diverse_starts"),
    "task_start_prob": ("task", "start_prob"), "frontier_start_prob": ("frontier", "start_prob"),
    "frontier_parent": ("frontier", "parent"), "frontier_radius": ("frontier", "radius"),
    "frontier_inner_radius": ("frontier", "inner_radius"),
    "frontier_candidates": ("frontier", "candidates"),
    "frontier_min_open": ("frontier", "min_open"),
    "frontier_goal_starts": ("frontier", "goal_starts"),
    "eval_prefer_pessimistic": ("eval", "prefer_pessimistic"), "td3_hidden": ("td3", "hidden"),
    "td3_batch_size": ("td3", "batch_size"), "td3_updates_per_step": ("td3", "updates_per_step"),
    "td3_sample_block": ("td3", "sample_block"), "td3_lr": ("td3", "lr"),
    "td3_clip_targets": ("td3", "clip_targets"), "td3_action_l2": ("td3", "action_l2"),
    "td3_dtype": ("td3", "dtype"), "shared_critic": ("td3", "shared_critic"),
    "discount": ("td3", "discount"), "replay_capacity": ("td3", "replay_capacity"),
    "her_strategy": ("td3", "her_strategy"), "her_relabel_prob": ("td3", "her_relabel_prob"),
    "action_noise": ("td3", "action_noise"), "random_action_prob": ("td3", "random_action_prob"),
    "mf_initial_random_prob": ("td3", "mf_initial_random_prob"),
    "mf_random_decay_successes": ("td3", "mf_random_decay_successes"),
    "option_init": ("chain", "option_init"),
    "global_option_timeout": ("chain", "global_option_timeout"),
    "initiation_period": ("chain", "initiation_period"), "dyn_hidden": ("dynamics", "hidden"),
    "dyn_ensemble": ("dynamics", "ensemble"), "dyn_batch_size": ("dynamics", "batch_size"),
    "dyn_lr": ("dynamics", "lr"), "dyn_updates_per_step": ("dynamics", "updates_per_step"),
    "dyn_pretrain_steps": ("dynamics", "pretrain_steps"),
    "model_capacity": ("dynamics", "capacity"), "mpc_samples": ("mpc", "samples"),
    "mpc_horizon": ("mpc", "horizon"), "mpc_discount": ("mpc", "discount"),
    "mpc_dtype": ("mpc", "dtype"), "mpc_backend": ("mpc", "backend"),
    "svm_backend": ("chain", "svm_backend"), "inband_eval_envs": ("eval", "inband_envs"),
    "inband_eval_window": ("eval", "inband_window"),
    "inband_eval_batched": ("eval", "inband_batched"), "eval_every": ("eval", "every"),
    "eval_episodes": ("eval", "episodes"), "checkpoint_every": ("run", "checkpoint_every"),
    "keep_checkpoints": ("run", "keep_checkpoints"), "preset": (None, "preset"),
}
DOTTED_NAMES: dict[str, str] = {flat: (f"{s}.{f}" if s else f)
                                for flat, (s, f) in FLAT_NAMES.items()}
"""Flat name -> the field's full name (`section.field`; the top-level fields: their name)."""
_BY_DOTTED = {dotted: flat for flat, dotted in DOTTED_NAMES.items()}
_FLAT_OF = {(s, f): flat for flat, (s, f) in FLAT_NAMES.items()}


def flat_name(name: str) -> str:
    """The flat name of a field given by its flat or its `section.field` name; a ValueError
    naming it (a retired field as removed, a typo with the closest names) otherwise."""
    if name in FLAT_NAMES:
        return name
    if name in _BY_DOTTED:
        return _BY_DOTTED[name]
    raise ValueError(unknown_fields_message([name]))


def unknown_fields_message(names) -> str:
    """The error for names that are no Config field: retired ones say so and what their value
    was; others list the closest field names."""
    names = sorted(names)
    retired = [n for n in names if n in RETIRED_FIELDS]
    if retired:
        said = ", ".join(f"{n} (it was {RETIRED_FIELDS[n]!r})" for n in retired)
        return (f"retired config field(s) {retired}: this version no longer has {said}; drop "
                f"them (saved runs that hold them at that value still load)")
    close = sorted({c for n in names for c in difflib.get_close_matches(
        n, list(FLAT_NAMES) + list(_BY_DOTTED), n=3)})
    hint = f"; did you mean {', '.join(close)}?" if close else ""
    return (f"unknown config field(s) {names}{hint} (valid fields: section.field or the flat "
            f"names; the list: dscpp_jax.config.FLAT_NAMES); e.g. "
            f"{', '.join(sorted(DOTTED_NAMES.values())[:3])}, ...")


def _check_section(section) -> None:
    """Type-check every field of a section (`check_field` without the CHOICES values: a saved run
    may hold a value this version dropped), naming a field as `section.field` (`TD3Section(
    batch_size=...)` is `td3.batch_size`, not `batch_size` or `td3_batch_size`)."""
    name = SECTION_NAMES[type(section)]
    for f in dataclasses.fields(section):
        check_field(f"{name}.{f.name}", getattr(section, f.name), values=False)


def flat_config(d: dict) -> dict:
    """A saved config (config.json's "config": nested by section, or flat as runs made before the
    sections wrote it) as {flat name: value}; a nested entry this version does not know becomes
    `section.field`."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if k in SECTIONS and isinstance(v, dict):
            for f, x in v.items():
                out[_FLAT_OF.get((k, f), f"{k}.{f}")] = x
        else:
            out[k] = v
    return out


@dataclass(frozen=True, init=False)
class Config:
    """Everything static about a training run (sizes, schedule, hyperparameters): what the run is
    (env, algo, subgoal, preset) and one section per component (task, run, td3, dynamics, mpc,
    chain, frontier, eval), each a frozen dataclass.

    `Config(...)` takes sections (`td3=TD3Section(...)`) and single fields by their flat name
    (`td3_lr=1e-4`) or full name (`**{"td3.lr": 1e-4}`), the others at their defaults.

    Units: env steps are steps of one environment unless a field says "all environments
    together"; distances are in the maze's x-y units (the ant's and the point mass's positions);
    cadences count `train_step` calls."""

    env: str = "point_u_maze"
    """environment name for `envs.make`: an ant maze (one of MAZES) or its point-mass twin
    (point_ + the maze)"""
    algo: str = "mb_dscpp"
    """the learner, one of ALGOS"""
    subgoal: str = "robust"
    """how a subgoal is chosen in the target option's initiation region: robust or dp"""
    preset: str = "paper"
    """the preset this config came from (one of PRESETS)"""
    task: TaskSection = dataclasses.field(default_factory=TaskSection)
    """the environment's physics and episodes"""
    run: RunSection = dataclasses.field(default_factory=RunSection)
    """seed, batching, schedule and checkpoints"""
    td3: TD3Section = dataclasses.field(default_factory=TD3Section)
    """TD3 + HER, replay and exploration"""
    dynamics: DynamicsSection = dataclasses.field(default_factory=DynamicsSection)
    """the learned dynamics model"""
    mpc: MPCSection = dataclasses.field(default_factory=MPCSection)
    """MPC over the learned model"""
    chain: ChainSection = dataclasses.field(default_factory=ChainSection)
    """the skill chain and its classifiers"""
    frontier: FrontierSection = dataclasses.field(default_factory=FrontierSection)
    """the chain's frontier"""
    eval: EvalSection = dataclasses.field(default_factory=EvalSection)
    """separate and in-band evaluation"""

    def __init__(self, **fields: Any):
        for f in dataclasses.fields(Config):
            object.__setattr__(self, f.name, f.default if f.default is not dataclasses.MISSING
                               else f.default_factory())
        _set_fields(self, fields, values=False)

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
    def option_policies(self) -> str:
        """What each option's policy pursues: "region" for the baselines dsc and dual (a TD3 per
        option on the observation alone, rewarded -1 per step and 0, done, on entering its target
        region: the parent's pessimistic region, the task goal for the goal option; the global
        option's TD3 learns from every transition at the task's reward); "goal" otherwise (a
        goal-conditioned TD3 with HER driven to a subgoal point, DSC++)."""
        return "region" if self.algo in ("dsc", "dual") else "goal"

    @property
    def per_option_td3(self) -> bool:
        """Whether each option slot has its own TD3 (region policies always; goal-conditioned
        policies with td3.shared_critic=False)."""
        return self.option_policies == "region" or not self.td3.shared_critic

    @property
    def exploration_per_option(self) -> bool:
        """Whether the model-free random-action schedule counts each option's own successes
        (dsc and dual, as the authors' per-option epsilon) rather than all options' together."""
        return self.algo in ("dsc", "dual")

    @property
    def effective_global_option_timeout(self) -> int:
        if self.chain.global_option_timeout > 0:
            return self.chain.global_option_timeout
        return 1 if self.algo in ("dsc", "dual") else self.chain.option_timeout

    @property
    def effective_initiation_period(self) -> int:
        if self.chain.initiation_period >= 0:
            return self.chain.initiation_period
        return 2 if self.algo in ("dsc", "dual") else 0

    @property
    def steps_per_iteration_total(self) -> int:
        return self.run.num_envs * self.run.steps_per_iter

    @property
    def td3_updates(self) -> int:
        """TD3 gradient steps per train_step."""
        return max(1, int(round(self.td3.updates_per_step * self.steps_per_iteration_total)))

    @property
    def dyn_updates(self) -> int:
        """Dynamics-model gradient steps per train_step (model-based algorithms only)."""
        if not self.model_based:
            return 0
        return max(1, int(round(self.dynamics.updates_per_step * self.steps_per_iteration_total)))

    @property
    def effective_random_prob(self) -> float:
        if self.td3.random_action_prob >= 0:
            return self.td3.random_action_prob
        return 0.1 if self.model_based else 0.2

    @property
    def effective_td3_lr(self) -> float:
        return self.td3.effective_lr(self.model_based)

    @property
    def inband_window(self) -> int:
        """K: finished in-band episodes that `inband/success_rate` averages over."""
        return self.eval.inband_window if self.eval.inband_window > 0 else self.eval.inband_envs

    @property
    def num_iterations(self) -> int:
        return -(-self.run.total_env_steps // self.steps_per_iteration_total)

    @property
    def frontier_on(self) -> bool:
        """Whether the skill chain uses the chain's frontier (frontier starts or parents)."""
        return self.hierarchical and (self.frontier.start_prob > 0 or self.frontier.parent)

    def inert_fields(self) -> frozenset:
        """Fields (flat names) this config's other settings leave without effect (comparing two
        configs, a difference in them changes nothing): the chain's frontier's parameters where
        the frontier is off, and the frontier starts' inner radius and goal starts where only
        frontier parents are on."""
        if not self.frontier_on:
            return frozenset({"frontier_radius", "frontier_inner_radius", "frontier_candidates",
                              "frontier_min_open", "frontier_goal_starts"})
        return frozenset() if self.frontier.start_prob > 0 else frozenset(
            {"frontier_inner_radius", "frontier_goal_starts"})

    # ------------------------------------------------------------------------------------------
    def get(self, name: str) -> Any:
        """The value of the field with flat or `section.field` name `name`."""
        section, field = FLAT_NAMES[flat_name(name)]
        return getattr(self if section is None else getattr(self, section), field)

    def override(self, **kw: Any) -> "Config":
        """A copy with some fields replaced, each given by its flat name (`td3_lr=1e-4`), its
        full name (`**{"td3.lr": 1e-4}`) or as a whole section (`td3=TD3Section(...)`); unknown
        names, and values that do not fit their field (`check_field`), raise a ValueError."""
        new = object.__new__(Config)
        for f in dataclasses.fields(Config):
            object.__setattr__(new, f.name, getattr(self, f.name))
        _set_fields(new, kw, values=True)
        return new

    def device_view(self) -> "Config":
        """The fields that shape the jitted computation; host-only fields (seed, schedule length,
        logging/checkpoint cadence, preset name) reset, so changing them never recompiles."""
        return self.override(**HOST_ONLY_DEFAULTS)

    def to_dict(self) -> dict:
        """The config as saved (config.json): the top-level fields and one mapping per section."""
        return dataclasses.asdict(self)

    def flat(self) -> dict:
        """{flat name: value} for every field (the table FLAT_NAMES' order)."""
        return {name: self.get(name) for name in FLAT_NAMES}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict) -> "Config":
        """The Config of a saved mapping, nested (`to_dict`) or flat (runs made before the
        sections); fields it lacks take `LEGACY_DEFAULTS`, else their defaults, and names this
        version does not know are dropped."""
        d = {**LEGACY_DEFAULTS, **flat_config(d)}
        return cls(**{k: v for k, v in d.items() if k in FLAT_NAMES})

    @classmethod
    def from_saved(cls, d: Any, defaults: Any = None, source: str = "this run") -> "Config":
        """The Config of a saved run (config.json's "config", nested or flat), checked against
        this version.

        Fields the run lacks (added since) take their defaults, which is what it used. Fields this
        version no longer has are ignored when they hold the value that meant "off" (the default
        recorded beside the run, `defaults`, else `RETIRED_FIELDS`); any other value raises a
        ValueError naming them, since the run's results depend on behaviour that is gone."""
        if not isinstance(d, dict):
            raise ValueError(f"{source}: config.json's \"config\" is not a mapping of Config fields")
        d = flat_config(d)
        off = {**RETIRED_FIELDS, **(flat_config(defaults) if isinstance(defaults, dict) else {})}
        _missing = object()
        gone = {k: v for k, v in d.items() if k not in FLAT_NAMES and off.get(k, _missing) != v}
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
        except (TypeError, ValueError) as e:
            raise ValueError(f"{source}: config.json's \"config\" does not fit this version's "
                             f"Config ({e})") from None

    def validate(self) -> "Config":
        """Raise a ValueError naming the fix for any impossible setting (a field of the wrong
        type or value, or settings that do not go together); return self."""
        def need(cond: bool, msg: str) -> None:
            if not cond:
                raise ValueError(f"invalid config: {msg}")

        check_fields(self)
        for name in ("num_envs", "steps_per_iter", "episode_length", "option_timeout", "buffer_len",
                     "gestation", "td3_batch_size", "dyn_batch_size", "mpc_samples", "mpc_horizon",
                     "eval_episodes", "max_pos_traj", "max_neg", "td3_hidden", "dyn_hidden",
                     "dyn_ensemble", "total_env_steps"):
            need(int(self.get(name)) >= 1, f"{name}={self.get(name)} must be >= 1")
        need(self.chain.max_options >= 3, f"max_options={self.chain.max_options} must be >= 3 "
             "(global, goal and at least one chain link)")
        need(self.task.warmup_episodes >= 0, "warmup_episodes must be >= 0")
        for name in ("eval_every", "checkpoint_every"):
            need(int(self.get(name)) >= 0,
                 f"{name}={self.get(name)} must be >= 0 (train_step calls between them; "
                 f"0: {'never' if name == 'eval_every' else 'only at exit'})")
        need(self.run.keep_checkpoints >= 1,
             f"keep_checkpoints={self.run.keep_checkpoints} must be >= 1")
        need(self.run.seed >= 0, f"seed={self.run.seed} must be >= 0 (seeds are non-negative "
             "integers, as --seeds takes them)")
        need(self.run.total_episodes >= 0, "total_episodes must be >= 0 (0: no episode limit)")
        need(self.task.goal_tolerance > 0, "goal_tolerance must be > 0")
        need(0.0 < self.td3.discount <= 1.0,
             f"discount={self.td3.discount} (td3.discount) must be in (0, 1]")
        need(0.0 < self.mpc.discount <= 1.0,
             f"mpc_discount={self.mpc.discount} (mpc.discount) must be in (0, 1]")
        need(not self.td3.clip_targets or self.td3.discount < 1.0,
             "td3_clip_targets needs discount < 1 (with discount 1 the values have no lower "
             "bound); lower discount or set td3_clip_targets=false")
        need(0.0 <= self.td3.her_relabel_prob <= 1.0, "her_relabel_prob must be in [0, 1]")
        need(self.td3.random_action_prob <= 1.0, "random_action_prob must be <= 1")
        for name in ("td3_updates_per_step", "dyn_updates_per_step"):
            need(self.get(name) >= 0, f"{name}={self.get(name)} ({DOTTED_NAMES[name]}) must be "
                 f">= 0 (gradient steps per stored env transition)")
        need(self.td3.sample_block >= 1,
             f"td3_sample_block must be >= 1 (1: one replay sample per gradient step), got "
             f"{self.td3.sample_block}")
        need(self.td3.action_l2 >= 0, "td3_action_l2 must be >= 0 (0: off)")
        need(self.run.group_size >= 1, f"group_size={self.run.group_size} must be >= 1")
        need(self.mpc.backend != "pallas" or self.mpc.dtype == "bfloat16",
             "mpc_backend=pallas computes in bfloat16: also set mpc_dtype=bfloat16 (or use "
             "mpc_backend=xla)")
        per_env = self.td3.replay_capacity // self.run.num_envs
        need(per_env >= max(2, self.run.steps_per_iter),
             f"replay_capacity={self.td3.replay_capacity} gives {per_env} steps per environment for "
             f"num_envs={self.run.num_envs}; raise replay_capacity to at least "
             f"{self.run.num_envs * max(2, self.run.steps_per_iter)}")
        need(per_env >= self.chain.option_timeout + 1,
             f"replay_capacity per environment ({per_env}) must exceed option_timeout="
             f"{self.chain.option_timeout} so HER can see whole option segments; raise replay_capacity")
        if self.model_based:
            mper = self.dynamics.capacity // self.run.num_envs
            need(mper >= max(2, self.run.steps_per_iter),
                 f"model_capacity={self.dynamics.capacity} too small for num_envs={self.run.num_envs} and "
                 f"steps_per_iter={self.run.steps_per_iter}; raise it to at least "
                 f"{self.run.num_envs * max(2, self.run.steps_per_iter)}")
        need(self.eval.inband_envs >= 0,
             f"inband_eval_envs={self.eval.inband_envs} must be >= 0 (0: no in-band evaluation; "
             f"e.g. 16 runs 16 evaluation episodes from the task start inside each train_step)")
        need(self.eval.inband_window >= 0,
             f"inband_eval_window={self.eval.inband_window} must be >= 0 (0: the last "
             f"inband_eval_envs finished in-band episodes)")
        need(self.chain.buffer_len < self.chain.option_timeout + 1,
             "buffer_len must be <= option_timeout")
        need(0.0 <= float(self.task.start_prob) <= 1.0,
             f"task_start_prob={self.task.start_prob} must be in [0, 1] (the share of training "
             f"episodes that start at the task start; 0: all diverse starts)")
        need(0.0 <= float(self.frontier.start_prob) <= 1.0
             and float(self.task.start_prob) + float(self.frontier.start_prob) <= 1.0,
             f"frontier_start_prob={self.frontier.start_prob} must be in [0, 1] and, with "
             f"task_start_prob={self.task.start_prob}, sum to at most 1 (the shares of training "
             f"episodes that start at the task start and on the chain's frontier)")
        need(self.frontier.start_prob == 0 or self.task.diverse_starts,
             "frontier_start_prob > 0 draws some of the diverse starts on the chain's frontier: "
             "it needs diverse_starts=true")
        need(self.frontier.start_prob == 0 and not self.frontier.parent or self.hierarchical,
             f"frontier_start_prob and frontier_parent act on the skill chain: algo={self.algo!r} "
             f"has none; use one of {HIERARCHICAL_ALGOS} or leave them off")
        need(not self.frontier.goal_starts or self.frontier.start_prob > 0,
             "frontier_goal_starts=true draws frontier starts next to the task goal: it needs "
             "frontier_start_prob > 0")
        need(0 <= self.frontier.inner_radius < self.frontier.radius,
             f"frontier_inner_radius={self.frontier.inner_radius} and frontier_radius="
             f"{self.frontier.radius}: need 0 <= frontier_inner_radius < frontier_radius")
        need(self.frontier.candidates >= 1 and self.frontier.min_open >= 1,
             f"frontier_candidates={self.frontier.candidates} and frontier_min_open="
             f"{self.frontier.min_open} must be >= 1")
        need(self.td3.shared_critic or not self.model_based,
             f"shared_critic=False (one TD3 per option) is implemented for the model-free "
             f"algorithms only ({', '.join(a for a in ALGOS if a not in MODEL_BASED_ALGOS)}): "
             f"algo={self.algo!r} plans with MPC, whose value term uses one critic for all "
             f"envs; set shared_critic=True or use algo='mf_dscpp'")
        need(self.chain.global_option_timeout >= 0,
             f"global_option_timeout={self.chain.global_option_timeout} must be >= 0 (0: the "
             f"algorithm's)")
        return self


# ------------------------------------------------------------------------------------------------
# Field checks
# ------------------------------------------------------------------------------------------------
SECTION_NAMES: dict[type, str] = {cls: name for name, cls in SECTIONS.items()}
_DECLARED = {(s, f.name): f for s, cls in ((None, Config), *((n, c) for n, c in SECTIONS.items()))
             for f in dataclasses.fields(cls)}
_FIELD_TYPES: dict[str, str] = {}
_DEFAULTS: dict[str, Any] = {}
for _flat, _where in FLAT_NAMES.items():
    _f = _DECLARED[_where]
    _FIELD_TYPES[_flat] = _f.type if isinstance(_f.type, str) else _f.type.__name__
    _DEFAULTS[_flat] = _f.default
assert set(_DECLARED) == set(FLAT_NAMES.values()) | {(None, s) for s in SECTIONS}
_TYPE_NAMES = {"int": "an integer", "float": "a number", "bool": "true or false",
               "str": "a string"}


def _set_fields(config: Config, fields: dict, values: bool) -> None:
    """Set `fields` (flat names, `section.field` names or whole sections) on a Config being
    built, checking each value (`check_field`; with `values`, the CHOICES too)."""
    bad = [k for k in fields if k not in FLAT_NAMES and k not in _BY_DOTTED and k not in SECTIONS]
    if bad:
        raise ValueError(unknown_fields_message(bad))
    changes: dict[str, dict[str, Any]] = {}
    for name, value in fields.items():
        if name in SECTIONS:
            if not isinstance(value, SECTIONS[name]):
                raise ValueError(f"invalid config: {name}={value!r}; {name} is a "
                                 f"{SECTIONS[name].__name__}")
            object.__setattr__(config, name, value)
            continue
        check_field(name, value, values)
        section, field = FLAT_NAMES[flat_name(name)]
        if section is None:
            object.__setattr__(config, field, value)
        else:
            changes.setdefault(section, {})[field] = value
    for section, change in changes.items():
        object.__setattr__(config, section, dataclasses.replace(getattr(config, section), **change))


def _one_of(choices) -> str:
    """The choices in words: `a, b or c` for up to three, else `one of a, b, c, d`."""
    names = [str(c) for c in choices]
    if len(names) <= 3:
        return ", ".join(names[:-1]) + " or " + names[-1] if len(names) > 1 else names[0]
    return "one of " + ", ".join(names)


def _type_ok(kind: str, value: Any) -> bool:
    if kind == "bool":
        return isinstance(value, bool)
    if kind == "int":
        return isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if kind == "float":
        return isinstance(value, numbers.Real) and not isinstance(value, bool)
    return isinstance(value, str)


def check_field(name: str, value: Any, values: bool = True) -> None:
    """Raise a ValueError naming the field (as given: flat or `section.field`), the value and what
    it takes if `value` does not fit Config field `name`: its declared type (a float field takes
    an int too) and, with `values`, for the fields of `CHOICES`, one of the listed values."""
    flat = flat_name(name)
    kind = _FIELD_TYPES[flat]
    if not _type_ok(kind, value):
        raise ValueError(f"invalid config: {name}={value!r} ({type(value).__name__}); {name} is "
                         f"{_TYPE_NAMES[kind]} ({kind}), e.g. {name}={_DEFAULTS[flat]!r}")
    if values and flat in CHOICES and value not in CHOICES[flat]:
        allowed = CHOICES[flat]
        say = (f"choose {_one_of(allowed)}" if len(allowed) > 3 else
               f"{name} must be {_one_of(allowed)}")
        raise ValueError(f"invalid config: {name}={value!r}; {say}")


def check_fields(config: Config, values: bool = True) -> None:
    """`check_field` for every field of `config`."""
    for name in FLAT_NAMES:
        check_field(name, config.get(name), values)


# ------------------------------------------------------------------------------------------------
# Presets
# ------------------------------------------------------------------------------------------------
# PRESET_TABLE[preset][(env selector, learner selector)] = field overrides.
#   env selector: "*" (every environment), a family of ENV_FAMILIES ("ant", "point") or an
#     environment name ("u_maze", "point_medium", ...);
#   learner selector: "*" (every learner), a class of LEARNER_CLASSES ("model_based",
#     "model_free") or an algorithm of ALGOS.
# `preset()` applies the entries that match, the least specific first: ordered by the env
# selector ("*", family, name), then by the learner selector ("*", class, algorithm); then the
# entries of FRONTIER_TABLE where the chain's frontier is on; then the caller's overrides.
# An environment is in one family and a learner in one class, so no two matching entries share
# a place in that order.
PRESET_TABLE: dict[str, dict[tuple[str, str], dict[str, Any]]] = {
    "paper": {
        ("*", "*"): dict(num_envs=1, steps_per_iter=1000, total_env_steps=2_001_000,
                         total_episodes=2001, eval_every=10, eval_episodes=1,
                         checkpoint_every=50),
        ("ant", "*"): dict(ant_integrator="RK4"),
    },
    "fast": {
        ("point", "*"): dict(
            num_envs=16, steps_per_iter=100, total_env_steps=100_000,
            episode_length=500, warmup_episodes=8, gestation=5,
            max_options=8, max_pos_traj=50, max_neg=50,
            td3_updates_per_step=0.25, td3_batch_size=256, td3_hidden=64, td3_lr=3e-4,
            replay_capacity=200_000, model_capacity=100_000,
            dyn_hidden=64, dyn_updates_per_step=0.02, dyn_pretrain_steps=300,
            dyn_batch_size=256, mpc_samples=128,
            eval_every=5, eval_episodes=8, checkpoint_every=10),
        ("ant", "*"): dict(
            num_envs=128, steps_per_iter=50, total_env_steps=4_000_000, total_episodes=2001,
            gestation=5, replay_capacity=1_000_000, model_capacity=300_000,
            dyn_updates_per_step=0.1, dyn_pretrain_steps=2000, mpc_samples=4096,
            mpc_dtype="bfloat16", max_options=24, td3_clip_targets=True,
            ant_integrator="RK4", td3_sample_block=32,
            inband_eval_envs=32, eval_every=0, eval_episodes=100, checkpoint_every=25),
        ("ant", "model_based"): dict(td3_updates_per_step=0.25, td3_batch_size=256, td3_lr=1e-4,
                                     td3_action_l2=0.0, td3_dtype="float32"),
        ("ant", "model_free"): dict(td3_updates_per_step=1.0, td3_batch_size=512, td3_lr=-1.0,
                                    td3_action_l2=1.0, td3_dtype="bfloat16"),
        # the paper's baselines: no action penalty (the original has none)
        ("ant", "dsc"): dict(td3_action_l2=0.0),
        ("ant", "dual"): dict(td3_action_l2=0.0),
        ("u_maze", "*"): dict(mpc_samples=2048),
        ("four_rooms", "*"): dict(gestation=10),
        ("medium", "mf_dscpp"): MEDIUM_MODEL_FREE_TD3,
        ("medium", "td3_her"): MEDIUM_MODEL_FREE_TD3,
    },
}
# FRONTIER_TABLE[preset][(env selector, learner selector)]: the entries applied, in the same
# order, where the chain's frontier is on: the preset has entries here, the environment and
# learner are in FRONTIER_CHAINS, and the caller does not turn diverse starts off.
FRONTIER_TABLE: dict[str, dict[tuple[str, str], dict[str, Any]]] = {
    "fast": {
        ("*", "*"): FRONTIER_PRESET,
        ("medium", "*"): dict(max_options=32),
        ("medium", "mb_dscpp"): dict(td3_updates_per_step=1.0),
    },
}


def _rank(selector: str, name: str, groups: dict[str, tuple[str, ...]]) -> int | None:
    """Where a selector that matches `name` goes in the merge order ("*", then a group of
    `groups`, then the name itself); None if it does not match."""
    if selector == "*":
        return 0
    if name in groups.get(selector, ()):
        return 1
    return 2 if selector == name else None


def matching_entries(table: dict[tuple[str, str], dict[str, Any]], env: str,
                     algo: str) -> list[tuple[tuple[str, str], dict[str, Any]]]:
    """The entries of one preset's table that apply to `env` and `algo`, in merge order."""
    ranked = []
    for (env_sel, learner_sel), entry in table.items():
        e, a = _rank(env_sel, env, ENV_FAMILIES), _rank(learner_sel, algo, LEARNER_CLASSES)
        if e is not None and a is not None:
            ranked.append(((e, a), (env_sel, learner_sel), entry))
    return [(key, entry) for _, key, entry in sorted(ranked, key=lambda r: r[0])]


def frontier_chain(name: str, env: str, algo: str, diverse_starts: bool = True) -> bool:
    """Whether preset `name` turns on the chain's frontier for `env` and `algo`."""
    return name in FRONTIER_TABLE and algo in FRONTIER_CHAINS.get(env, ()) and bool(diverse_starts)


def preset_fields(name: str, env: str, algo: str, diverse_starts: bool = True,
                  beyond_paper: bool = True) -> dict[str, Any]:
    """The fields preset `name` sets for `env` and `algo`, before the caller's overrides:
    env, algo and preset, then the matching `PRESET_TABLE` entries and, where the chain's frontier
    is on, the matching `FRONTIER_TABLE` entries, merged in that order (later entries win).
    `beyond_paper=False` leaves out the entries beyond the paper (the frontier's and
    `BEYOND_PAPER_ENTRIES`)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {PRESETS}")
    if env not in ENV_NAMES:
        raise ValueError(f"unknown env name {env!r} for preset {name!r}; valid names: "
                         f"{list(ENV_NAMES)}")
    if algo not in ALGOS:
        raise ValueError(f"unknown learner algo={algo!r} for preset {name!r}; choose one of "
                         f"{list(ALGOS)}")
    fields: dict[str, Any] = dict(env=env, algo=algo, preset=name)
    for _, entry in matching_entries(PRESET_TABLE[name], env, algo):
        if beyond_paper or not any(entry is e for e in BEYOND_PAPER_ENTRIES):
            fields.update(entry)
    if beyond_paper and frontier_chain(name, env, algo, diverse_starts):
        for _, entry in matching_entries(FRONTIER_TABLE[name], env, algo):
            fields.update(entry)
    return fields


def paper_rule_overrides(name: str, env: str, algo: str) -> dict[str, Any]:
    """The overrides that turn preset `name`'s settings beyond the paper off for `env` and
    `algo` (the chain's frontier and `BEYOND_PAPER_ENTRIES`): each field whose value differs,
    at its value without them, leaving out fields that are then without effect
    (`Config.inert_fields`); {} where the preset adds nothing beyond the paper."""
    full = Config(**preset_fields(name, env, algo))
    paper = Config(**preset_fields(name, env, algo, beyond_paper=False))
    skip = paper.inert_fields()
    return {k: v for k, v in paper.flat().items() if k not in skip and full.get(k) != v}


def preset(name: str = "fast", env: str = "point_u_maze", algo: str = "mb_dscpp",
           **overrides: Any) -> Config:
    """Preset `name` (one of PRESETS) for environment `env` (one of ENV_NAMES) and learner `algo`
    (one of ALGOS), with the field overrides applied last.

    The preset's fields come from `PRESET_TABLE` and `FRONTIER_TABLE` (`preset_fields` says how
    they merge); with diverse_starts=False among the overrides the chain's frontier stays off.
    Unknown presets, environments, learners and fields raise a ValueError listing the known
    ones, and so does a value of the wrong type for its field; as for any Config, `validate()`
    checks the rest."""
    diverse = overrides.get("diverse_starts", overrides.get("task.diverse_starts", True))
    fields = preset_fields(name, env, algo, diverse)
    bad = [k for k in overrides if k not in FLAT_NAMES and k not in _BY_DOTTED]
    if bad:
        raise ValueError(unknown_fields_message(bad))
    fields.update({flat_name(k): v for k, v in overrides.items()})
    return Config(**fields)


def parse_value(field_name: str, text: str) -> Any:
    """Convert a command-line string (`--set field=text`, the field by its flat or its
    `section.field` name) to the type of Config field `field_name`; a ValueError names the field,
    what it takes and an example. (The values of `CHOICES` fields are checked by
    `Config.validate`.)"""
    if field_name not in FLAT_NAMES and field_name not in _BY_DOTTED:
        raise ValueError(unknown_fields_message([field_name]).replace(
            f"field(s) [{field_name!r}]", f"field {field_name!r}"))
    t = _FIELD_TYPES[flat_name(field_name)]
    example = _DEFAULTS[flat_name(field_name)]
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
    except (ValueError, OverflowError):
        raise ValueError(f"--set {field_name}={text!r}: {field_name} is {_TYPE_NAMES[t]}, e.g. "
                         f"--set {field_name}={example}") from None
    return text
