"""The MJX ant maze: D4RL/OGBench ant on `mujoco.mjx` directly, walls generated from the map.

Physics (the DSC++ setting): 8 motors with gear 30 and ctrlrange [-1, 1] (actions in [-1, 1] are
torques of +-30), timestep 0.02 s x 5 frames = 0.1 s per env step, observation qpos[:15] +
qvel[:14] (29 numbers, torso x, y first), reset qpos0 + U(-0.1, 0.1) (quaternion renormalised) and
qvel 0.1 N(0, 1), 1000-step episodes, sparse goal reward. Integrator: semi-implicit Euler by
default (D4RL uses RK4, available as `integrator="RK4"`: MJX runs the full forward pass, contacts
and solver included, four times per physics step, 3.9x slower on an H200). Newton solver, 4
iterations / 8 line-search steps, dense jacobian.

Contacts are pruned for speed: no self-collision; the floor touches only the foot spheres and the
torso; walls sit on their own collision bit and touch the torso, knee and foot spheres with
frictionless single-row (condim 1) contacts. Walls are the map's merged wall boxes
(`wall_mode="static"`) or, by default, 3 cell-sized proxy boxes (mocap bodies) that every physics
step are placed on the wall cells of the quadrant the torso is in, the only walls within the ant's
reach, so contact cost does not grow with the maze (the merged boxes stay in the MJCF for
drawing). As a backstop a torso that ends an env step inside a wall cell gets its previous x, y
back with zero x, y velocity.

The interface follows Brax (`reset`, `step`, `observation_size`, `action_size`, `State` with the
`mjx.Data` as pipeline_state), but physics is stepped with `mujoco.mjx.step`, not through Brax's
pipeline (much faster). `mujoco_c_step` steps the identical model in MuJoCo C (tests, benchmarks).
"""
from __future__ import annotations

import contextlib
import dataclasses
import warnings
from typing import Optional

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from brax.envs.base import State
from mujoco import mjx

from dscpp_jax.envs import goals
from dscpp_jax.envs.goal_env import GoalMazeEnv
from dscpp_jax.envs.maze_layout import MazeLayout

# Actuator order of the D4RL ant.
ACTUATED_JOINTS = ("hip_4", "ankle_4", "hip_1", "ankle_1", "hip_2", "ankle_2", "hip_3", "ankle_3")
TORSO_RADIUS = 0.25
LIMB_RADIUS = 0.08
TORSO_HEIGHT = 0.75
# Farthest any ant collision point gets from the torso centre (in x, y): hip 0.28 + thigh 0.28 +
# shin 0.57 + foot radius 0.08 = 1.21, plus 0.1 of torso travel within one physics step.
ANT_REACH = 1.31
PROXY_MIN_CELL = 2.0 * ANT_REACH
NUM_PROXIES = 3
PROXY_PARK_Z = -50.0  # proxies of free cells wait far below the floor


def use_proxies(layout: MazeLayout, cfg: "AntConfig") -> bool:
    if cfg.wall_mode == "auto":
        return layout.cell_size >= PROXY_MIN_CELL
    if cfg.wall_mode == "proxy" and layout.cell_size < PROXY_MIN_CELL:
        raise ValueError(f"wall_mode='proxy' needs cell_size >= {PROXY_MIN_CELL:.2f} (the ant's reach "
                         f"x 2), got {layout.cell_size}; use wall_mode='static'")
    return cfg.wall_mode == "proxy"


def proxy_positions(layout: MazeLayout, wall_grid, torso_xy, wall_height: float, xp=jnp):
    """(NUM_PROXIES, 3) centres of the proxy wall boxes for a torso at torso_xy.

    The candidates are the x-neighbour, y-neighbour and diagonal neighbour cells on the side of
    the torso's offset from its cell centre; wall cells get a proxy, free ones park it below the
    floor. xp = jnp (in the env) or np (the MuJoCo C helper).
    """
    S = layout.cell_size
    rows, cols = wall_grid.shape
    col = xp.floor(torso_xy[0] / S + 0.5).astype(xp.int32) + layout.origin[1]
    row = xp.floor(torso_xy[1] / S + 0.5).astype(xp.int32) + layout.origin[0]
    cx = (col - layout.origin[1]) * S
    cy = (row - layout.origin[0]) * S
    sx = xp.where(torso_xy[0] >= cx, 1, -1)
    sy = xp.where(torso_xy[1] >= cy, 1, -1)
    cand_r = xp.stack([row, row + sy, row + sy])
    cand_c = xp.stack([col + sx, col, col + sx])
    inside = (cand_r >= 0) & (cand_r < rows) & (cand_c >= 0) & (cand_c < cols)
    is_wall = xp.where(inside, wall_grid[xp.clip(cand_r, 0, rows - 1), xp.clip(cand_c, 0, cols - 1)], True)
    x = (cand_c - layout.origin[1]) * S
    y = (cand_r - layout.origin[0]) * S
    z = xp.where(is_wall, wall_height / 2.0, PROXY_PARK_Z)
    return xp.stack([x, y, z], axis=-1).astype(xp.float32)


@dataclasses.dataclass(frozen=True)
class AntConfig:
    timestep: float = 0.02
    frame_skip: int = 5
    integrator: str = "Euler"  # "Euler" (semi-implicit, default, fast) or "RK4" (D4RL)
    # Euler integrates joint damping implicitly (MuJoCo's default); False makes it explicit.
    eulerdamp: bool = True
    # D4RL's soft ant contacts (solref/solimp of its ant.xml default geom class). MuJoCo's
    # stiffer defaults (solimp "0.9 0.95 0.001") tip the ant over far more often under aggressive
    # actions (experiments/results/ant_flips.md). D4RL also has a 1 cm contact margin; MJX does not
    # follow MuJoCo C with a margin (3e-2 apart within 10 steps, against 1e-5 without), so it is 0.
    contact_margin: float = 0.0
    contact_solref: str = "0.02 1"
    contact_solimp: str = "0.8 0.8 0.01"
    gear: float = 30.0
    solver: str = "Newton"
    # Newton with 4 iterations / 8 line-search steps converges on these contacts: MJX then tracks
    # MuJoCo C to ~1e-4 over 30 env steps; with 1 iteration both solvers stop unconverged, in
    # different places, and the trajectories part after the first contacts (see bench_env.md).
    solver_iterations: int = 4
    ls_iterations: int = 8
    jacobian: str = "dense"
    wall_height: float = 2.0
    wall_contacts: str = "torso_knees_feet"  # or "torso_feet", "torso"
    # "proxy": the ant collides with 3 cell-sized wall boxes (mocap bodies) moved before every
    # physics step to the wall cells of the quadrant its torso is in (the only walls within its
    # reach), so contact cost does not grow with the maze; the merged wall boxes are drawn but do
    # not collide. "static": the merged wall boxes collide. "auto": proxy when cells are large
    # enough (cell_size >= PROXY_MIN_CELL), else static.
    wall_mode: str = "auto"
    max_contact_points: int = -1  # MJX broad-phase numerics (-1 = off)
    max_geom_pairs: int = -1
    torso_wall_backstop: bool = True
    reset_noise_scale: float = 0.1
    episode_length: int = goals.EPISODE_LENGTH
    goal_tolerance: float = goals.GOAL_TOLERANCE
    # Wall margin of the diverse-start sampler: the torso keeps 1.0 from walls so the legs
    # (0.9 reach in the rest pose) start clear of them; Ant-Reacher starts span [-9.5, 9.5]^2.
    start_margin: float = 1.0
    # Physics back end: "jax" (MJX in JAX, differentiable, any platform) or "warp" (MuJoCo Warp
    # through MJX, needs `warp-lang`; 2-3x faster on GPUs). Warp keeps its contact and
    # constraint arrays in buffers shared by all worlds of a batch, sized here: `warp_worlds` is
    # the largest number of envs stepped together (every vmapped axis multiplied out: seeds x
    # envs), `warp_contacts_per_world` and `warp_constraints_per_world` the room per world.
    physics: str = "jax"
    warp_worlds: int = 128
    warp_contacts_per_world: int = 16
    warp_constraints_per_world: int = 64

    def __post_init__(self):
        if self.physics not in ("jax", "warp"):
            raise ValueError(f"physics must be 'jax' or 'warp', got {self.physics!r}")
        if min(self.warp_worlds, self.warp_contacts_per_world, self.warp_constraints_per_world) < 1:
            raise ValueError("warp_worlds, warp_contacts_per_world and warp_constraints_per_world "
                             "must be >= 1")
        if self.integrator not in ("RK4", "Euler", "implicitfast"):
            raise ValueError(f"integrator must be 'RK4', 'Euler' or 'implicitfast', got {self.integrator!r}")
        if self.wall_contacts not in ("torso_knees_feet", "torso_feet", "torso"):
            raise ValueError("wall_contacts must be 'torso_knees_feet', 'torso_feet' or 'torso', "
                             f"got {self.wall_contacts!r}")
        if self.wall_mode not in ("auto", "proxy", "static"):
            raise ValueError(f"wall_mode must be 'auto', 'proxy' or 'static', got {self.wall_mode!r}")
        if self.frame_skip < 1 or self.episode_length < 1:
            raise ValueError("frame_skip and episode_length must be >= 1")


_LEGS = (  # (name, hip offset direction, ankle axis, ankle range)
    ("1", (1, 1), "-1 1 0", "30 70"),
    ("2", (-1, 1), "1 1 0", "-70 -30"),
    ("3", (-1, -1), "-1 1 0", "-70 -30"),
    ("4", (1, -1), "1 1 0", "30 70"),
)


def ant_mjcf(layout: MazeLayout, cfg: AntConfig = AntConfig()) -> str:
    """MJCF text of the ant in the maze. Collision bits: 1 = floor, 2 = walls."""
    numerics = []
    # MJX reads these by numeric id: they must come FIRST in <custom>.
    if cfg.max_contact_points >= 0:
        numerics.append(f'<numeric data="{cfg.max_contact_points}" name="max_contact_points"/>')
    if cfg.max_geom_pairs >= 0:
        numerics.append(f'<numeric data="{cfg.max_geom_pairs}" name="max_geom_pairs"/>')
    custom = f"<custom>{''.join(numerics)}</custom>" if numerics else ""
    hz = cfg.wall_height / 2.0
    proxies = use_proxies(layout, cfg)
    wall_col = 'contype="0" conaffinity="2" condim="1" priority="1"'
    static_col = 'contype="0" conaffinity="0" group="1"' if proxies else wall_col
    walls = "\n".join(
        f'    <geom name="wall_{k}" type="box" pos="{cx:g} {cy:g} {hz:g}" size="{hx:g} {hy:g} {hz:g}" '
        f'{static_col} rgba="0.7 0.5 0.3 1"/>'
        for k, (cx, cy, hx, hy) in enumerate(layout.wall_boxes))
    if proxies:
        h = layout.cell_size / 2.0
        walls += "".join(
            f'\n    <body name="wall_proxy_{k}" mocap="true" pos="0 0 {PROXY_PARK_Z:g}">'
            f'<geom name="wall_proxy_{k}" type="box" size="{h:g} {h:g} {hz:g}" {wall_col} rgba="0 0 0 0"/></body>'
            for k in range(NUM_PROXIES))
    knee_type = 2 if cfg.wall_contacts == "torso_knees_feet" else 0
    foot_type = 3 if cfg.wall_contacts != "torso" else 1
    legs = []
    for name, (sx, sy), axis, rng in _LEGS:
        a = f"{0.2 * sx:g} {0.2 * sy:g} 0.0"
        f = f"{0.4 * sx:g} {0.4 * sy:g} 0.0"
        legs.append(f"""
      <body name="leg_{name}" pos="0 0 0">
        <geom name="aux_{name}_geom" type="capsule" fromto="0 0 0 {a}" size="{LIMB_RADIUS}"/>
        <body name="aux_{name}" pos="{a}">
          <joint name="hip_{name}" type="hinge" axis="0 0 1" range="-30 30"/>
          <geom name="leg_{name}_geom" type="capsule" fromto="0 0 0 {a}" size="{LIMB_RADIUS}"/>
          <body name="shin_{name}" pos="{a}">
            <joint name="ankle_{name}" type="hinge" axis="{axis}" range="{rng}"/>
            <geom name="ankle_{name}_geom" type="capsule" fromto="0 0 0 {f}" size="{LIMB_RADIUS}"/>
            <geom name="knee_{name}" type="sphere" size="{LIMB_RADIUS}" mass="0" contype="{knee_type}"/>
            <geom name="foot_{name}" type="sphere" pos="{f}" size="{LIMB_RADIUS}" mass="0" contype="{foot_type}"/>
          </body>
        </body>
      </body>""")
    motors = "\n".join(
        f'    <motor joint="{j}" gear="{cfg.gear:g}" ctrlrange="-1 1" ctrllimited="true"/>'
        for j in ACTUATED_JOINTS)
    size = max(abs(v) for v in layout.bounds) + 10.0
    return f"""<mujoco model="ant_{layout.name}">
  <compiler angle="degree" coordinate="local" inertiafromgeom="true"/>
  <option timestep="{cfg.timestep:g}" integrator="{cfg.integrator}" solver="{cfg.solver}"
          iterations="{cfg.solver_iterations}" ls_iterations="{cfg.ls_iterations}" jacobian="{cfg.jacobian}">
    {'' if cfg.eulerdamp else '<flag eulerdamp="disable"/>'}
  </option>
  {custom}
  <default>
    <joint armature="1" damping="1" limited="true"/>
    <geom contype="0" conaffinity="0" condim="3" density="5.0" friction="1 0.5 0.5" margin="{cfg.contact_margin:g}"
          solref="{cfg.contact_solref}" solimp="{cfg.contact_solimp}" rgba="0.8 0.6 0.4 1"/>
  </default>
  <worldbody>
    <light directional="true" diffuse="1 1 1" pos="0 0 10" dir="0 0 -1"/>
    <geom name="floor" type="plane" pos="0 0 0" size="{size:g} {size:g} 1" contype="0" conaffinity="1" condim="3" rgba="0.8 0.9 0.8 1"/>
{walls}
    <body name="torso" pos="{layout.start_xy[0]:g} {layout.start_xy[1]:g} {TORSO_HEIGHT}">
      <joint name="root" type="free" armature="0" damping="0" limited="false"/>
      <geom name="torso_geom" type="sphere" size="{TORSO_RADIUS}" contype="3"/>{''.join(legs)}
    </body>
  </worldbody>
  <actuator>
{motors}
  </actuator>
</mujoco>
"""


# MuJoCo Warp's per-world overflow bits that mean dropped contacts or constraint rows (all but the
# solver's iteration-limit notes, bits 9 and 10).
WARP_BUFFER_OVERFLOWS = (1 << 12) - 1 - (1 << 9) - (1 << 10)


def warp_available() -> bool:
    """Whether MuJoCo Warp can run here (`warp-lang` importable by MJX)."""
    try:
        from mujoco.mjx import warp as mjx_warp
    except ImportError:
        return False
    return bool(getattr(mjx_warp, "WARP_INSTALLED", False))


def _warp_model_and_data(mj_model: mujoco.MjModel, d0: mujoco.MjData, cfg: AntConfig):
    """MuJoCo Warp model and the data template for `cfg.warp_worlds` worlds (MJX's warp impl)."""
    if not warp_available():
        raise ValueError("physics='warp' needs the warp-lang package (pip install -e '.[warp]', "
                         "or '.[cuda]' on a GPU host); use physics='jax' without it")
    import warp
    # Warp's start-up banner and per-module load lines are information, not news: print warnings
    # and errors only (a level set by the user stays when it is already quieter)
    warp.config.log_level = max(warp.config.log_level, warp.LOG_WARNING)
    model = mjx.put_model(mj_model, impl="warp")
    # Overflows are detected from the data (AntMazeEnv.physics_overflow); the solver's
    # "iteration limit reached" notes would print on every step of a capped Newton solve.
    impl = model.opt._impl
    if hasattr(impl, "warn_overflow"):
        model = model.replace(opt=model.opt.replace(_impl=impl.replace(warn_overflow=0)))
    data = mjx.put_data(mj_model, d0, impl="warp",
                        naconmax=cfg.warp_worlds * cfg.warp_contacts_per_world,
                        njmax=cfg.warp_constraints_per_world)
    return model, _deterministic_template(data)


def _deterministic_template(data):
    """The Warp data template with its uninitialised buffer set.

    MuJoCo Warp's ``put_data`` allocates ``contact.geomcollisionid`` without setting it, so the
    template held whatever the allocator left there. The physics never reads those entries before
    its collision pass writes them, but ``init`` bakes the template into its program as a
    constant, so the program, and with it the key of JAX's persistent compilation cache, differed
    in every process: each warm start compiled ``init`` again (5-6 s on a GPU). Zero is what MuJoCo
    Warp's own reset writes there."""
    impl = data._impl
    if not hasattr(impl, "contact__geomcollisionid"):
        return data
    return data.replace(_impl=impl.replace(
        contact__geomcollisionid=jnp.zeros_like(impl.contact__geomcollisionid)))


def body_points(m: mujoco.MjModel, geom_xpos, geom_xmat, n: int = 5):
    """Points along every ant capsule centre line and every sphere centre (for wall tests).

    geom_xpos (..., ngeom, 3), geom_xmat (..., ngeom, 3, 3) -> (..., P, 3). NumPy.
    """
    pts = []
    for g in range(m.ngeom):
        if m.geom_bodyid[g] == 0 or m.body_mocapid[m.geom_bodyid[g]] >= 0:
            continue  # world and proxy-wall geoms
        pos = geom_xpos[..., g, :]
        if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE:
            half = m.geom_size[g, 1]
            axis = geom_xmat[..., g, :, 2]
            for t in np.linspace(-1.0, 1.0, n):
                pts.append(pos + t * half * axis)
        else:
            pts.append(pos)
    return np.stack(pts, axis=-2)


class AntMazeEnv(GoalMazeEnv):
    """Goal-conditioned MJX ant maze with a Brax-compatible interface."""

    observation_size = 29
    action_size = 8
    backend = "mjx"

    def __init__(self, layout: MazeLayout, config: AntConfig = AntConfig()):
        super().__init__(layout, config)
        self.name = layout.name
        self.xml = ant_mjcf(layout, config)
        self.mj_model = mujoco.MjModel.from_xml_string(self.xml)
        self.uses_proxies = use_proxies(layout, config)
        self._wall_grid_np = layout.wall_grid()
        self._wall_grid = jnp.asarray(self._wall_grid_np)
        self._init_qpos = jnp.asarray(self.mj_model.qpos0, jnp.float32)
        d0 = mujoco.MjData(self.mj_model)
        self.set_proxies_c(d0)
        mujoco.mj_forward(self.mj_model, d0)
        if config.physics == "warp":
            self.mjx_model, self._data0 = _warp_model_and_data(self.mj_model, d0, config)
        else:
            self.mjx_model = mjx.put_model(self.mj_model)
            self._data0 = mjx.put_data(self.mj_model, d0)

    @property
    def naconmax(self) -> int:
        """Contacts the Warp buffers hold over all worlds (0 with MJX-JAX: no shared buffer)."""
        c = self.config
        return c.warp_worlds * c.warp_contacts_per_world if c.physics == "warp" else 0

    def physics_overflow(self, data) -> jax.Array:
        """True when the last physics step found more contacts (summed over all worlds) or
        constraint rows (in this world) than the Warp buffers hold: the excess was dropped. Always
        False with MJX-JAX."""
        if self.config.physics != "warp":
            return jnp.zeros((), bool)
        return (data._impl.overflow & WARP_BUFFER_OVERFLOWS) != 0

    def warp_one_world(self):
        """A one-world MuJoCo Warp model and data of this env's model, on Warp's current device:
        the env's solver options (those that pick kernels, e.g. ``warn_overflow``) and its
        per-world contact and constraint sizes. What `build_warp_kernels` steps to build the
        kernels; benchmarks and tests use it to step MuJoCo Warp outside JAX."""
        from mujoco.mjx.third_party import mujoco_warp as mjwarp
        m = mjwarp.put_model(self.mj_model)
        impl = self.mjx_model.opt._impl
        for f in dataclasses.fields(m.opt):
            v = getattr(impl, f.name, None)
            if isinstance(v, (bool, int, float)) and type(v) is type(getattr(m.opt, f.name)):
                setattr(m.opt, f.name, v)
        d = mjwarp.make_data(self.mj_model, nworld=1, naconmax=self.config.warp_contacts_per_world,
                             njmax=self.config.warp_constraints_per_world)
        return m, d

    def build_warp_kernels(self, device: Optional[str] = None, workers: int = 0) -> bool:
        """Build MuJoCo Warp's kernels for this model now, outside JAX: one physics step of a
        one-world batch through MuJoCo Warp itself, on a Warp stream of its own (Warp compiles a
        kernel at its first launch and keeps it in its kernel cache; the JAX step finds it there).
        Safe to run in a thread while XLA compiles, since it never touches XLA's stream. ``device``:
        a Warp device name (default: the first CUDA device). ``workers``: the step's modules are
        first found by a dry run and compiled on this many threads (`envs.warp_kernels`; 0: one
        per CPU core up to 16, 1: one after another at their first launch). Returns False where
        there is nothing to build (MJX-JAX physics, or no such device)."""
        if self.config.physics != "warp":
            return False
        import warp as wp
        from mujoco.mjx.third_party import mujoco_warp as mjwarp
        if device is None:
            if not wp.is_cuda_available():
                return False
            device = "cuda:0"
        dev = wp.get_device(device)
        with wp.ScopedDevice(dev):
            stream = wp.Stream(dev) if dev.is_cuda else None
            with wp.ScopedStream(stream) if stream is not None else contextlib.nullcontext():
                m, d = self.warp_one_world()
                if workers != 1:
                    from dscpp_jax.envs.warp_kernels import load_modules, modules_launched
                    try:
                        mods = modules_launched(lambda: mjwarp.step(m, d))
                    except Exception as e:  # noqa: BLE001 - the step below still builds them
                        warnings.warn(f"MuJoCo Warp's kernels build one after another: the dry "
                                      f"run of the step failed ({type(e).__name__}: {e})")
                        mods = []
                    load_modules(mods, workers)
                mjwarp.step(m, d)   # loads whatever the dry run missed
            if stream is not None:
                wp.synchronize_stream(stream)
        return True

    @property
    def dt(self) -> float:
        return self.config.timestep * self.config.frame_skip

    def __repr__(self):
        return f"AntMazeEnv({self.layout.name!r})"

    # ---- MuJoCo C twin (tests, benchmarks) ------------------------------------------------------
    def set_proxies_c(self, d: mujoco.MjData):
        """Place the proxy walls for MuJoCo C data `d` (no-op with static walls)."""
        if self.uses_proxies:
            d.mocap_pos[:] = proxy_positions(self.layout, self._wall_grid_np, d.qpos[:2],
                                             self.config.wall_height, xp=np)

    def mujoco_c_step(self, d: mujoco.MjData, action):
        """One env step of the identical physics in MuJoCo C (no backstop, no reward)."""
        d.ctrl[:] = np.clip(action, -1.0, 1.0)
        for _ in range(self.config.frame_skip):
            self.set_proxies_c(d)
            mujoco.mj_step(self.mj_model, d)

    def _physics_step(self, d):
        if self.uses_proxies:
            d = d.replace(mocap_pos=proxy_positions(self.layout, self._wall_grid, d.qpos[:2],
                                                    self.config.wall_height))
        return mjx.step(self.mjx_model, d)

    # ---- API ---------------------------------------------------------------------------------
    def reset_at(self, key, xy) -> State:
        """Episode with the torso at xy (+ reset noise: qpos U(-0.1, 0.1), qvel 0.1 N(0, 1))."""
        k1, k2 = jax.random.split(key)
        c = self.config.reset_noise_scale
        qpos = self._init_qpos.at[:2].set(jnp.asarray(xy, jnp.float32))
        qpos = qpos + jax.random.uniform(k1, qpos.shape, minval=-c, maxval=c)
        qpos = qpos.at[3:7].set(qpos[3:7] / jnp.linalg.norm(qpos[3:7]))
        qvel = c * jax.random.normal(k2, (self.mj_model.nv,))
        # The template holds the kinematics of the nominal pose; mjx.step recomputes everything
        # from qpos/qvel, and skipping mjx.forward here keeps reset cheap to compile.
        data = self._data0.replace(qpos=qpos, qvel=qvel)
        zero = jnp.zeros((), jnp.float32)
        return State(pipeline_state=data, obs=self._obs(data), reward=zero, done=zero, metrics={},
                     info=goals.initial_info(self.goal))

    def step(self, state: State, action) -> State:
        prev = state.pipeline_state
        a = jnp.clip(jnp.nan_to_num(jnp.asarray(action, jnp.float32)), -1.0, 1.0)
        data = prev.replace(ctrl=a)
        def frame(_, carry):
            d, over = carry
            d = self._physics_step(d)
            return d, over | self.physics_overflow(d)

        data, overflow = jax.lax.fori_loop(0, self.config.frame_skip, frame,
                                           (data, jnp.zeros((), bool)))
        if self.config.torso_wall_backstop:
            inside = self.layout.in_wall(data.qpos[:2])
            qpos = data.qpos.at[:2].set(jnp.where(inside, prev.qpos[:2], data.qpos[:2]))
            qvel = data.qvel.at[:2].set(jnp.where(inside, 0.0, data.qvel[:2]))
            data = data.replace(qpos=qpos, qvel=qvel)
        obs = self._obs(data)
        nan = ~jnp.all(jnp.isfinite(obs))
        # Physics blew up: keep the last finite state (the episode ends; the caller resets).
        data = data.replace(
            qpos=jnp.where(nan, prev.qpos, data.qpos), qvel=jnp.where(nan, prev.qvel, data.qvel),
            qacc_warmstart=jnp.where(nan, 0.0, data.qacc_warmstart))
        obs, reward, done, info = goals.finish_step(state.info, obs, state.obs, self.episode_length,
                                                    self.goal_tolerance, nan=nan,
                                                    overflow=overflow)
        return state.replace(pipeline_state=data, obs=obs, reward=reward, done=done, info=info)

    def upright(self, obs):
        """World-z component of the torso's z axis: 1 upright, below 0 on its back.

        obs[3:7] is the torso quaternion (w, x, y, z); the z axis's world z is 1 - 2 (x^2 + y^2).
        """
        q = jnp.asarray(obs)[..., 3:7]
        return 1.0 - 2.0 * (q[..., 1] ** 2 + q[..., 2] ** 2)

    @staticmethod
    def _obs(data):
        return jnp.concatenate([data.qpos[:15], data.qvel[:14]]).astype(jnp.float32)
