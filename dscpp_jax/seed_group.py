"""Seed groups: many seeds of one Config trained in one jitted program, sharded over devices and
hosts with `jax.sharding`.

    import jax, dscpp_jax
    cfg = dscpp_jax.preset("fast", env="point_u_maze", algo="mb_dscpp")
    states = dscpp_jax.init_group([0, 1, 2, 3], cfg)       # leading axis: the seeds
    for _ in range(30):
        states, metrics = dscpp_jax.train_step_group(states)   # metrics["..."]: (4,)
    summaries, result = dscpp_jax.evaluate_group(states)       # one dict per seed

A group state is a `TrainState` whose leaves carry a leading seed axis of length N. Seed ``s`` of
the group starts from exactly ``init(jax.random.PRNGKey(s), cfg)``: `init_group` runs that
function once per seed and stacks the results, so a group is the same experiment as N separate
runs. One step vmaps `train_step_impl` over the seed axis inside `jax.shard_map` over a
one-dimensional device mesh whose axis is named ``seeds``: every device advances its own N / D
seeds and no data crosses devices during a step. The seeds of a group differ from separate runs
only by floating-point rounding: XLA computes the vmapped matrix products as batched products,
which may sum in another order (about 1e-7 relative after an iteration on a CPU).

Which leaves are split over the devices is decided in one place, `leaf_spec`: a leaf whose leading
dimension is the group size is split along ``seeds``; any other leaf (a scalar, or an array that
is shared by the whole group, such as a physics back end's contact arrays that all worlds share)
is replicated and given to the vmapped step unbatched (``in_axes=None``).

Multi-host: call `initialize_distributed` (``jax.distributed.initialize``) in every process before
anything else touches JAX, then build the mesh over ``jax.devices()`` (all processes' devices).
Group states are then global arrays of which each process holds its own seeds; `to_host` gathers
them (``multihost_utils.process_allgather``), and `GroupCheckpointer` saves and restores them
with orbax (each process writes its shards). On CPUs the cross-process collectives use gloo
(``jax_cpu_collectives_implementation``, JAX's default on CPUs), which `initialize_distributed`
selects.

The number of seeds must be a multiple of the number of devices (`check_group_size` names the
valid sizes); groups are never padded.

A program over several devices is lowered and compiled with JAX's GSPMD partitioner instead of
Shardy (`GroupProgram`): with jax 0.11.2 XLA's GPU compiler segfaulted in its Shardy-to-XLA pass
on every ant group program over two H100s (MJX or MuJoCo Warp physics, model-free or
model-based), while the point-mass programs compiled either way. One-device programs keep JAX's
default.
"""
from __future__ import annotations

import contextlib
import functools
import os
import re
from typing import Any, Dict, List, Optional, Sequence, Tuple

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from dscpp_jax import trainer as T
from dscpp_jax.checkpoint import save_error, CKPT_DIR, NONE_SAVED, NoCheckpointError, as_stored, from_stored, \
    quiet_orbax
from dscpp_jax.config import Config
from dscpp_jax.evaluate import evaluate_episodes_impl, summarize

try:    # JAX's registry of types that vmap batches as a whole (MuJoCo Warp's Data registers there)
    from jax._src.interpreters.batching import vmappables as _VMAPPABLES
except ImportError:     # pragma: no cover - older or newer JAX without the registry
    _VMAPPABLES = {}
try:    # the switch between the Shardy and the GSPMD partitioner
    from jax._src.config import use_shardy_partitioner as _use_shardy_partitioner
except ImportError:     # pragma: no cover - a JAX without the option has no Shardy either
    _use_shardy_partitioner = None

SEED_AXIS = "seeds"
PyTree = Any


# ------------------------------------------------------------------------------------------------
# Seeds from text
# ------------------------------------------------------------------------------------------------
def parse_seeds(text: str) -> Tuple[int, ...]:
    """"0-7" -> (0, ..., 7); "0-3,7,9" -> (0, 1, 2, 3, 7, 9). Ranges include both ends."""
    seeds: List[int] = []
    parts = [p.strip() for p in str(text).split(",")]
    for part in parts:
        m = re.fullmatch(r"(\d+)\s*-\s*(\d+)", part) or re.fullmatch(r"(\d+)", part)
        if not m:
            raise ValueError(f"--seeds expects non-negative integers and ranges like 0-7 or "
                             f"0-3,7,9; cannot read {part!r} in {text!r}")
        lo = int(m.group(1))
        hi = int(m.group(2)) if m.lastindex == 2 else lo
        if hi < lo:
            raise ValueError(f"--seeds range {part!r} runs backwards; write it as {hi}-{lo}")
        seeds.extend(range(lo, hi + 1))
    dup = sorted({s for s in seeds if seeds.count(s) > 1})
    if dup:
        raise ValueError(f"--seeds {text!r} names seed(s) {dup} more than once")
    return tuple(seeds)


def format_seeds(seeds: Sequence[int]) -> str:
    """(0, 1, 2, 3, 7, 9) -> "0-3_7_9" (for directory names)."""
    out, seeds = [], list(seeds)
    i = 0
    while i < len(seeds):
        j = i
        while j + 1 < len(seeds) and seeds[j + 1] == seeds[j] + 1:
            j += 1
        out.append(str(seeds[i]) if i == j else f"{seeds[i]}-{seeds[j]}")
        i = j + 1
    return "_".join(out)


# ------------------------------------------------------------------------------------------------
# Devices, hosts and shardings
# ------------------------------------------------------------------------------------------------
def initialize_distributed(coordinator: Optional[str] = None, num_processes: Optional[int] = None,
                           process_id: Optional[int] = None) -> None:
    """Join a multi-process run (``jax.distributed.initialize``); call before any JAX computation.

    Missing arguments come from ``JAX_COORDINATOR_ADDRESS``, ``JAX_NUM_PROCESSES`` and
    ``JAX_PROCESS_ID``; where all are missing, JAX detects a cluster (SLURM, Open MPI, ...).
    On CPUs, cross-process collectives go through gloo."""
    coordinator = coordinator or os.environ.get("JAX_COORDINATOR_ADDRESS")
    if num_processes is None and os.environ.get("JAX_NUM_PROCESSES"):
        num_processes = int(os.environ["JAX_NUM_PROCESSES"])
    if process_id is None and os.environ.get("JAX_PROCESS_ID"):
        process_id = int(os.environ["JAX_PROCESS_ID"])
    if coordinator is not None and (num_processes is None or process_id is None):
        raise ValueError("a multi-process run needs --num-processes N and --process-id I (or "
                         "JAX_NUM_PROCESSES / JAX_PROCESS_ID) along with --coordinator HOST:PORT")
    try:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    except Exception:  # noqa: BLE001 - a JAX without the option
        pass
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                               process_id=process_id)


def seed_mesh(devices: Optional[Sequence[Any]] = None) -> Mesh:
    """A one-dimensional mesh named ``seeds`` over ``devices`` (default: every device of every
    process)."""
    devices = list(jax.devices() if devices is None else devices)
    return Mesh(np.asarray(devices, dtype=object), (SEED_AXIS,))


def valid_group_sizes(num_devices: int, up_to: int = 64) -> List[int]:
    return [k for k in range(num_devices, max(up_to, num_devices) + 1, num_devices)]


def check_group_size(n: int, mesh: Mesh) -> None:
    d = int(mesh.size)
    if n < 1:
        raise ValueError("a seed group needs at least one seed")
    if n % d:
        sizes = ", ".join(map(str, valid_group_sizes(d, max(4 * d, n + d))[:6]))
        raise ValueError(f"{n} seeds do not divide evenly over {d} devices; use a group size "
                         f"that is a multiple of {d} ({sizes}, ...) or fewer devices "
                         f"(e.g. CUDA_VISIBLE_DEVICES)")


def leaf_spec(leaf: Any, n: int) -> P:
    """THE sharding rule of a group state: split a leaf whose leading dimension is the group size
    along ``seeds``; replicate any other leaf (it is then shared by all seeds of the group)."""
    shape = getattr(leaf, "shape", ())
    return P(SEED_AXIS) if len(shape) >= 1 and shape[0] == n else P()


def _is_spec(x: Any) -> bool:
    return isinstance(x, P)


def group_specs(tree: PyTree, n: int) -> PyTree:
    """`leaf_spec` over a pytree (a group state, or its `jax.eval_shape`)."""
    return jax.tree_util.tree_map(lambda x: leaf_spec(x, n), tree)


def group_shardings(tree: PyTree, mesh: Mesh, n: Optional[int] = None) -> PyTree:
    """The NamedSharding of every leaf of a group pytree over `mesh` (see `leaf_spec`)."""
    n = group_size(tree) if n is None else n
    return jax.tree_util.tree_map(lambda s: NamedSharding(mesh, s), group_specs(tree, n),
                                  is_leaf=_is_spec)


def group_size(states: PyTree) -> int:
    """N of a group state (the leading axis of its iteration counter)."""
    it = states.counters.iteration if hasattr(states, "counters") else \
        jax.tree_util.tree_leaves(states)[0]
    if getattr(it, "ndim", 0) < 1:
        raise ValueError("not a group state: its counters have no seed axis (use init_group)")
    return int(it.shape[0])


def mesh_of(states: PyTree) -> Mesh:
    """The mesh a group state lives on (a mesh over all devices when it is not yet sharded)."""
    sh = getattr(states.counters.iteration, "sharding", None)
    if isinstance(sh, NamedSharding) and SEED_AXIS in sh.mesh.axis_names:
        return sh.mesh
    return seed_mesh()


def _spec_key(states: PyTree, n: int):
    specs = group_specs(states, n)
    leaves, treedef = jax.tree_util.tree_flatten(specs, is_leaf=_is_spec)
    return treedef, tuple(leaves)


def _vmappable(x: Any) -> bool:
    """A type that vmap batches as a whole with an int axis (it decides itself which of its fields
    carry the axis): MuJoCo Warp's Data, whose contact buffers all worlds share."""
    return type(x) in _VMAPPABLES


def _vmap_axes(treedef, specs) -> PyTree:
    """vmap's in_axes/out_axes for a group state: 0 for a seed-axis leaf, None for a shared one,
    and 0 for a vmappable node as a whole (its own batching rule skips its shared fields)."""
    spec_tree = jax.tree_util.tree_unflatten(treedef, list(specs))
    return jax.tree_util.tree_map(
        lambda s: 0 if _vmappable(s) or s == P(SEED_AXIS) else None, spec_tree,
        is_leaf=lambda x: _is_spec(x) or _vmappable(x))


def uses_gspmd(mesh: Mesh) -> bool:
    """Whether the group programs over `mesh` are partitioned by GSPMD rather than Shardy: every
    mesh of more than one device (see the module's docstring)."""
    return int(mesh.size) > 1


def _partitioner(gspmd: bool):
    if not gspmd or _use_shardy_partitioner is None:
        return contextlib.nullcontext()
    return _use_shardy_partitioner(False)


class GroupProgram:
    """A jitted group program (`train_step_group`'s, `evaluate_group`'s) that traces, lowers and
    compiles under the partitioner its mesh needs (`uses_gspmd`). Call it like the jitted
    function, or ahead of time: ``program.lower(*args).compile()``."""

    def __init__(self, jitted, mesh: Mesh):
        self.jitted = jitted
        self.gspmd = uses_gspmd(mesh)

    def __call__(self, *args):
        with _partitioner(self.gspmd):
            return self.jitted(*args)

    def lower(self, *args) -> "_Lowered":
        with _partitioner(self.gspmd):
            return _Lowered(self.jitted.lower(*args), self.gspmd)


class _Lowered:
    """A lowered group program whose `compile` keeps the partitioner it was lowered with."""

    def __init__(self, lowered, gspmd: bool):
        self.lowered, self.gspmd = lowered, gspmd

    def compile(self, *args, **kwargs):
        with _partitioner(self.gspmd):
            return self.lowered.compile(*args, **kwargs)

    def __getattr__(self, name):
        return getattr(self.lowered, name)


def _put(states: PyTree, mesh: Mesh, n: int) -> PyTree:
    """Place (or leave) a group state on `mesh` with the group shardings."""
    shardings = group_shardings(states, mesh, n)
    ok = all(getattr(x, "sharding", None) == s for x, s in
             zip(jax.tree_util.tree_leaves(states), jax.tree_util.tree_leaves(shardings)))
    return states if ok else jax.device_put(states, shardings)


# ------------------------------------------------------------------------------------------------
# init / train_step / evaluate over a group
# ------------------------------------------------------------------------------------------------
def group_shapes(config: Config, n: int):
    """(the group's config, one seed's abstract TrainState, the group's abstract TrainState).

    The group's shapes are those vmap makes: every leaf gets the seed axis, except the buffers
    that MuJoCo Warp shares between all worlds of a batch (they stay unbatched, sized for the
    group through `group_size`)."""
    config = T.resolve_physics(config.validate()).override(group_size=n)
    T.make_env(config.device_view())   # build the env outside any trace (it is cached)
    one = jax.eval_shape(lambda k: T.init_impl(k, config), jax.random.PRNGKey(0))
    like = jax.eval_shape(jax.vmap(lambda k: T.init_impl(k, config)),
                          jax.ShapeDtypeStruct((n,) + one.key.shape, one.key.dtype))
    return config, one, like


def init_group(seeds: Sequence[int], config: Config, mesh: Optional[Mesh] = None) -> T.TrainState:
    """A group state for `seeds` (leading axis: the seeds, in the order given), sharded over
    `mesh` (default: all devices). Seed ``seeds[i]`` is exactly ``init(PRNGKey(seeds[i]),
    config)``. Each process initialises only the seeds that land on its own devices."""
    seeds = tuple(int(s) for s in seeds)
    n = len(seeds)
    if len(set(seeds)) != n:
        raise ValueError(f"seeds {list(seeds)} name a seed more than once")
    mesh = seed_mesh() if mesh is None else mesh
    check_group_size(n, mesh)
    config, one, like = group_shapes(config, n)
    flat_one = jax.tree_util.tree_leaves(one)
    flat_sh, treedef = jax.tree_util.tree_flatten(group_shardings(like, mesh, n))
    flat_like = jax.tree_util.tree_leaves(like)
    batched = [x.shape == (n,) + o.shape for x, o in zip(flat_like, flat_one)]
    per_leaf: List[List[Any]] = [[] for _ in flat_like]
    # every seed-axis leaf has the same seeds on a device (the counters have the seed axis)
    j0 = batched.index(True)
    index_map = flat_sh[j0].addressable_devices_indices_map(flat_like[j0].shape)
    for device, index in index_map.items():
        ids = range(n)[index[0]]
        with jax.default_device(device):
            parts = [jax.tree_util.tree_leaves(T.init(jax.random.PRNGKey(seeds[i]), config))
                     for i in ids]
            for j in range(len(flat_like)):
                x = jnp.stack([p[j] for p in parts]) if batched[j] else parts[0][j]
                per_leaf[j].append(jax.device_put(x, device))
        del parts
    leaves = [jax.make_array_from_single_device_arrays(x.shape, s, arrs)
              for x, s, arrs in zip(flat_like, flat_sh, per_leaf)]
    return jax.tree_util.tree_unflatten(treedef, leaves)


def _group_body(treedef, specs):
    axes = _vmap_axes(treedef, specs)

    def step(states, active):
        def one(state, on):
            # under vmap a cond on `on` would run both branches anyway: step every seed, keep
            # the old state of the frozen ones. Work that only some seeds need is skipped when
            # none needs it (train_step_impl's seed_axis).
            new, m = T.train_step_impl(state, seed_axis=T.SEED_AXIS)
            m = {k: jnp.where(on, v, jnp.nan) for k, v in m.items()}
            return T.select_train_state(on, new, state), m
        return jax.vmap(one, in_axes=(axes, 0), out_axes=(axes, 0), axis_name=T.SEED_AXIS)(
            states, active)
    return step


@functools.lru_cache(maxsize=None)
def _step_fn(mesh: Mesh, treedef, specs: tuple):
    in_specs = jax.tree_util.tree_unflatten(treedef, list(specs))
    f = jax.shard_map(_group_body(treedef, specs), mesh=mesh,
                      in_specs=(in_specs, P(SEED_AXIS)), out_specs=(in_specs, P(SEED_AXIS)),
                      check_vma=False)
    shard = jax.tree_util.tree_map(lambda s: NamedSharding(mesh, s), in_specs, is_leaf=_is_spec)
    seeds = NamedSharding(mesh, P(SEED_AXIS))
    return GroupProgram(jax.jit(f, in_shardings=(shard, seeds), out_shardings=(shard, seeds)),
                        mesh)


def train_step_group(states: T.TrainState, active: Optional[Any] = None,
                     mesh: Optional[Mesh] = None) -> Tuple[T.TrainState, Dict[str, jax.Array]]:
    """One iteration of every seed of the group in one jitted program (compiles once per Config,
    group size and mesh); metrics have shape (N,). `active` (N,) bool, optional: seeds marked
    False keep their state unchanged (their metrics are NaN), so a seed that finished its
    schedule stops where a separate run of it would have stopped."""
    n = group_size(states)
    mesh = mesh_of(states) if mesh is None else mesh
    check_group_size(n, mesh)
    treedef, specs = _spec_key(states, n)
    states = _put(states, mesh, n)
    seeds_sh = NamedSharding(mesh, P(SEED_AXIS))
    if active is None:
        active = np.ones((n,), bool)
    active = _global(np.asarray(active, bool).reshape(n), seeds_sh)
    return _step_fn(mesh, treedef, specs)(states, active)


def group_step_program(states: T.TrainState, mesh: Optional[Mesh] = None):
    """(the step's `GroupProgram`, states placed on the mesh, all-active mask): what
    `train_step_group` calls, for ahead-of-time use (``fn.lower(states, active).compile()``, e.g.
    to time compilation)."""
    n = group_size(states)
    mesh = mesh_of(states) if mesh is None else mesh
    check_group_size(n, mesh)
    treedef, specs = _spec_key(states, n)
    active = _global(np.ones((n,), bool), NamedSharding(mesh, P(SEED_AXIS)))
    return _step_fn(mesh, treedef, specs), _put(states, mesh, n), active


def _global(x: np.ndarray, sharding: NamedSharding) -> jax.Array:
    """A host array (the same in every process) as a global array with `sharding`."""
    return jax.make_array_from_callback(x.shape, sharding, lambda idx: x[idx])


EVAL_KEY_BASE = 1_000_003   # as dscpp_jax.evaluate.evaluate's default key


@functools.lru_cache(maxsize=None)
def _eval_fn(mesh: Mesh, treedef, specs: tuple, num_episodes: int, with_starts: bool,
             with_key: bool, explore: bool = False):
    in_specs = jax.tree_util.tree_unflatten(treedef, list(specs))
    axes = _vmap_axes(treedef, specs)

    def body(states, key, starts):
        def one(state, k):
            if not with_key:    # evaluate()'s default: a key from the seed's own iteration
                k = jax.random.fold_in(jax.random.PRNGKey(EVAL_KEY_BASE), state.counters.iteration)
            return evaluate_episodes_impl(state, k, num_episodes,
                                          starts if with_starts else None, explore=explore)
        return jax.vmap(one, in_axes=(axes, None))(states, key)

    f = jax.shard_map(body, mesh=mesh, in_specs=(in_specs, P(), P()), out_specs=P(SEED_AXIS),
                      check_vma=False)
    shard = jax.tree_util.tree_map(lambda s: NamedSharding(mesh, s), in_specs, is_leaf=_is_spec)
    rep = NamedSharding(mesh, P())
    return GroupProgram(jax.jit(f, in_shardings=(shard, rep, rep),
                                out_shardings=NamedSharding(mesh, P(SEED_AXIS))), mesh)


def evaluate_group(states: T.TrainState, key: Optional[jax.Array] = None,
                   num_episodes: Optional[int] = None, starts=None, mesh: Optional[Mesh] = None,
                   explore: bool = False):
    """Evaluate every seed of the group in one call (vmap of the evaluation over the seeds).

    Returns (one summary dict per seed, the EvalResult with a leading seed axis, on the host).
    Without `key`, seed i uses the key `dscpp_jax.evaluate` would use for it alone (from its
    iteration), so each seed's numbers are those of a separate evaluation; with `key`, every
    seed uses that key. `explore`: with training's action noise (`dscpp_jax.evaluate.evaluate`)."""
    n = group_size(states)
    mesh = mesh_of(states) if mesh is None else mesh
    cfg: Config = states.config
    if starts is not None:
        starts = np.asarray(starts, np.float32).reshape(-1, 2)
        num_episodes = int(starts.shape[0])
    num_episodes = int(num_episodes or cfg.eval.episodes)
    treedef, specs = _spec_key(states, n)
    states = _put(states, mesh, n)
    rep = NamedSharding(mesh, P())
    k = np.asarray(jax.random.key_data(key) if key is not None and jax.dtypes.issubdtype(
        key.dtype, jax.dtypes.prng_key) else (key if key is not None else jax.random.PRNGKey(0)))
    s = np.zeros((1, 2), np.float32) if starts is None else starts
    fn = _eval_fn(mesh, treedef, specs, num_episodes, starts is not None, key is not None,
                  bool(explore))
    res = to_host(fn(states, _global(np.asarray(k), rep), _global(s, rep)))
    return [summarize(index_tree(res, i)) for i in range(n)], res


# ------------------------------------------------------------------------------------------------
# Host access
# ------------------------------------------------------------------------------------------------
def to_host(tree: PyTree) -> PyTree:
    """NumPy copies of a pytree of (possibly multi-process, global) arrays, in every process."""
    if jax.process_count() > 1:
        return multihost_utils.process_allgather(tree, tiled=True)
    return jax.device_get(tree)


def index_tree(tree: PyTree, i: int, n: Optional[int] = None) -> PyTree:
    """Seed i of a host group pytree (leaves without the seed axis are shared, so kept whole)."""
    if n is None:
        n = group_size(tree) if hasattr(tree, "counters") else None

    def take(x):
        if not hasattr(x, "shape"):
            return x
        if n is None or (x.ndim >= 1 and x.shape[0] == n):
            return x[i]
        return x
    return jax.tree_util.tree_map(take, tree)


def seed_state(states: T.TrainState, i: int) -> T.TrainState:
    """Seed i of a group as an ordinary single-seed TrainState on the default device (works with
    `train_step`, `evaluate`, `make_policy`, ...)."""
    host = index_tree(to_host(states), i, group_size(states))
    return jax.tree_util.tree_map(jnp.asarray, host)


# ------------------------------------------------------------------------------------------------
# Checkpoints of a whole group
# ------------------------------------------------------------------------------------------------
def _empty(x) -> bool:
    return hasattr(x, "shape") and int(np.prod(x.shape)) == 0


class GroupCheckpointer:
    """Orbax checkpoints of a whole group state under GROUP_DIR/checkpoints/<iteration>/.

    Works with global arrays: in a multi-process run every process calls `save` and `restore`,
    each writes and reads its own seeds (the directory must be shared by the processes).
    Zero-size leaves, which orbax refuses, are stored as one-element placeholders."""

    def __init__(self, group_dir: str, keep: int = 2):
        quiet_orbax()
        self._ocp = ocp
        self.group_dir = group_dir
        self.directory = os.path.abspath(os.path.join(group_dir, CKPT_DIR))
        opts = ocp.CheckpointManagerOptions(max_to_keep=max(1, keep), create=True)
        self.manager = ocp.CheckpointManager(self.directory, options=opts)

    def save(self, step: int, states: PyTree, wait: bool = True) -> None:
        """`wait=False` returns once orbax has copied the states to host memory; the files are
        written in the background and the next `save`, `wait`, `latest_step` or `close` waits
        for them (every process calls these at the same iterations)."""
        self.wait()
        storable = jax.tree_util.tree_map(
            lambda x: np.zeros((1,), x.dtype) if _empty(x) else x, as_stored(states))
        try:
            self.manager.save(int(step), args=self._ocp.args.StandardSave(storable), force=True)
        except Exception as e:  # noqa: BLE001 - orbax / tensorstore wrap OSErrors in many types
            raise save_error(e, self.directory, self.group_dir, int(step), self._steps()) from e
        if wait:
            self.wait()

    def _steps(self) -> list:
        return sorted(int(s) for s in self.manager.all_steps())

    def wait(self) -> None:
        """Wait for a save still being written; a failed one raises a CheckpointError."""
        try:
            self.manager.wait_until_finished()
        except Exception as e:  # noqa: BLE001
            raise save_error(e, self.directory, self.group_dir, kept=self._steps()) from e

    def latest_step(self) -> Optional[int]:
        self.wait()
        return self.manager.latest_step()

    def restore(self, like: PyTree, mesh: Optional[Mesh] = None,
                step: Optional[int] = None) -> PyTree:
        """Restore into the structure of `like` (a group state or its `jax.eval_shape`), sharded
        over `mesh` (default: `like`'s mesh). The mesh may differ from the one that saved."""
        step = self.latest_step() if step is None else step
        if step is None:
            raise NoCheckpointError(f"no checkpoint found under {self.directory}: {NONE_SAVED}")
        have = sorted(int(x) for x in self.manager.all_steps())
        if int(step) not in have:
            raise NoCheckpointError(f"no checkpoint of step {step} under {self.directory}; it "
                                    f"holds steps {have}")
        n = group_size(like)
        mesh = (mesh_of(like) if hasattr(like.counters.iteration, "sharding") else seed_mesh()) \
            if mesh is None else mesh
        full_like = like
        like = as_stored(like)
        shardings = as_stored(group_shardings(full_like, mesh, n))
        abstract = jax.tree_util.tree_map(
            lambda x, s: np.zeros((1,), x.dtype) if _empty(x)
            else jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s), like, shardings)
        stored = self.manager.restore(step, args=self._ocp.args.StandardRestore(abstract))

        def back(x, l, s):
            if _empty(l):
                return jax.jit(lambda: jnp.zeros(l.shape, l.dtype), out_shardings=s)()
            return x
        return from_stored(jax.tree_util.tree_map(back, stored, like, shardings), full_like)

    def close(self) -> None:
        self.manager.wait_until_finished()
        self.manager.close()
