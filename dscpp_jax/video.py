"""MP4 videos of evaluation episodes, drawn with MuJoCo's renderer (`mujoco.Renderer`).

    from dscpp_jax import video
    paths = video.render_run(cfg, state, "runs/<run>/videos", episodes=2)

The episodes are the run's deterministic evaluation episodes (`evaluate_episodes(...,
record=True)` keeps the per-step observations, subgoals and, for the MJX ant, qpos). Each frame
shows the maze, the task goal (gold disc of the goal tolerance and a gold ball), the agent coloured
by the running option (the ant's torso or the point mass, plus a halo disc under it) in the colours
of the trajectory plots (`plots.option_color`), the option's subgoal (a ball and a translucent disc
of the goal tolerance in the option's colour, joined to the agent by a line), the path so far
coloured by option, and a white disc where the episode started.

Two cameras: ``topdown`` sees the whole maze from above (x to the right, y up, as in the plots)
and ``follow`` looks at the agent from behind and above, moving with it. Each camera writes its own
file, ``eval_topdown.mp4`` and ``eval_follow.mp4``, with all episodes one after the other (the
last frame of each held for `hold_s` seconds); ``eval_video.json`` beside them says which episode
is which and what each option's colour is.

The ant is drawn from its own MJCF (the merged wall boxes; the invisible proxy walls it collides
with are not drawn) with qpos copied into a MuJoCo C `MjData` and `mj_forward`. The point-mass
envs have no MuJoCo model: `point_mjcf` builds a draw-only one from the layout's wall boxes with a
mocap ball for the point.

Rendering back end: `select_gl_backend` keeps a ``MUJOCO_GL`` set by the user, else takes the
first of EGL and OSMesa that can render (probed in a subprocess), and fails with the Debian
packages to install when neither can. Encoding: H.264 (yuv420p) through the ffmpeg binary that the
``imageio-ffmpeg`` wheel ships (``pip install -e '.[video]'``; `make install` includes it).

Rolling out and drawing can happen on different machines: `record_run` + `save_record` keep the
episodes (positions, options, subgoals, qpos) in a small ``.npz`` on a host with no OpenGL or
ffmpeg (a GPU training host, say), and `load_record` + `render_record` draw them elsewhere from
the run's config alone, without its checkpoint.
"""
from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import time
import warnings
from typing import Dict, Iterable, List, Optional, Sequence, Tuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from dscpp_jax import trainer as T
from dscpp_jax.evaluate import evaluate_episodes
from dscpp_jax.plots import option_color

CAMERAS = ("topdown", "follow")
GL_BACKENDS = ("egl", "osmesa")
GOAL_RGBA = (1.0, 0.84, 0.0, 1.0)     # matplotlib's "gold", the goal star of the plots
START_RGBA = (1.0, 1.0, 1.0, 1.0)     # white: the plots' green start would read as option 2
WALL_RGBA = "0.7 0.5 0.3 1"           # as the ant's MJCF
FLOOR_RGBA = "0.8 0.9 0.8 1"
MAX_TRAIL = 250                       # at most this many path segments per frame
GL_INSTALL_HINT = ("install Mesa's EGL (Debian/Ubuntu: apt-get install libegl1 libegl-mesa0 "
                   "libgl1-mesa-dri) or OSMesa (apt-get install libosmesa6); on an NVIDIA host "
                   "the driver's libEGL (then MUJOCO_GL=egl)")


class VideoError(RuntimeError):
    """A video cannot be made; the message names the fix."""


# ------------------------------------------------------------------------------------------------
# OpenGL back end
# ------------------------------------------------------------------------------------------------
_PROBE = """
import mujoco
m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><light pos="0 0 3"/>'
                                   '<geom type="sphere" size="1"/></worldbody></mujoco>')
d = mujoco.MjData(m)
mujoco.mj_forward(m, d)
r = mujoco.Renderer(m, 32, 32)
r.update_scene(d)
assert r.render().any(), "blank frame"
print("ok")
"""
_backend: Optional[str] = None


def _probe(backend: str, timeout: float = 120.0) -> Tuple[bool, str]:
    """Can a fresh Python render a frame with MUJOCO_GL=backend? (ok, last line of the error)."""
    env = dict(os.environ, MUJOCO_GL=backend, PYOPENGL_PLATFORM=backend)
    try:
        with warnings.catch_warnings():   # JAX warns about any fork; this one execs at once
            warnings.simplefilter("ignore", RuntimeWarning)
            p = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True,
                               text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return False, f"timed out after {timeout:.0f}s"
    if p.returncode == 0 and "ok" in p.stdout:
        return True, ""
    lines = [ln for ln in (p.stderr or p.stdout).strip().splitlines() if ln.strip()]
    return False, lines[-1] if lines else f"exit status {p.returncode}"


def _activate(backend: str) -> None:
    """Make `mujoco.Renderer` use `backend`, also when mujoco was imported before MUJOCO_GL was
    set (mujoco picks its GL context class at import)."""
    os.environ["MUJOCO_GL"] = backend
    if backend in ("egl", "osmesa"):
        os.environ.setdefault("PYOPENGL_PLATFORM", backend)
    if "mujoco" not in sys.modules:
        return
    from mujoco.rendering.classic import gl_context
    if getattr(gl_context, "_MUJOCO_GL", None) == backend:
        return
    if backend == "egl":
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        from mujoco.osmesa import GLContext
    elif backend == "glfw":
        from mujoco.glfw import GLContext
    else:
        return
    gl_context.GLContext = GLContext


def select_gl_backend() -> str:
    """The OpenGL back end for rendering: ``$MUJOCO_GL`` when set, else the first of
    ``GL_BACKENDS`` that renders a test frame. Raises VideoError naming the packages to install."""
    global _backend
    if _backend is not None:
        return _backend
    want = os.environ.get("MUJOCO_GL", "").strip().lower()
    if want:
        _activate(want)
        _backend = want
        return want
    errors = []
    for b in GL_BACKENDS:
        ok, err = _probe(b)
        if ok:
            _activate(b)
            _backend = b
            return b
        errors.append(f"{b}: {err}")
    raise VideoError("no OpenGL back end for MuJoCo rendering (" + "; ".join(errors) + "): "
                     + GL_INSTALL_HINT)


def _renderer(model, width: int, height: int, max_geom: int = 10000):
    backend = select_gl_backend()
    model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), width)
    model.vis.global_.offheight = max(int(model.vis.global_.offheight), height)
    try:
        return mujoco.Renderer(model, height=height, width=width, max_geom=max_geom)
    except Exception as e:  # noqa: BLE001 - any GL failure gets the same advice
        raise VideoError(f"cannot create a MuJoCo rendering context with MUJOCO_GL={backend} "
                         f"({type(e).__name__}: {e}); {GL_INSTALL_HINT}, or unset MUJOCO_GL to "
                         f"pick one automatically") from e


SOFTWARE_GL = ("llvmpipe", "softpipe", "swrast", "osmesa", "software")


def gl_renderer_name(renderer) -> str:
    """The OpenGL renderer string of a `mujoco.Renderer`'s context ('' when it cannot be read)."""
    try:
        renderer._gl_context.make_current()
        from OpenGL import GL
        name = GL.glGetString(GL.GL_RENDERER)
        return name.decode() if isinstance(name, bytes) else str(name or "")
    except Exception:  # noqa: BLE001 - only used to pick a default
        return ""


def is_software_gl(renderer) -> bool:
    """Rendering on the CPU (Mesa llvmpipe, OSMesa): shadow maps cost 20x a frame there."""
    name = gl_renderer_name(renderer).lower()
    return select_gl_backend() == "osmesa" or any(k in name for k in SOFTWARE_GL)


# ------------------------------------------------------------------------------------------------
# MP4 files
# ------------------------------------------------------------------------------------------------
def _ffmpeg():
    try:
        import imageio_ffmpeg
    except ImportError as e:
        raise VideoError("writing MP4 needs imageio-ffmpeg: pip install -e '.[video]' "
                         "(or pip install imageio-ffmpeg)") from e
    return imageio_ffmpeg


def check_encoder() -> None:
    """Raise VideoError naming the fix when MP4 cannot be written (no imageio-ffmpeg)."""
    _ffmpeg()


def check_options(cameras: Iterable[str] = CAMERAS, width: int = 480, height: int = 480,
                  fps: float = 30.0, every: int = 1, max_steps: Optional[int] = None,
                  crf: int = 23) -> None:
    """Raise VideoError for options that cannot make a video (before anything compiles)."""
    cameras = list(cameras)
    bad = [c for c in cameras if c not in CAMERAS]
    if bad or not cameras:
        raise VideoError(f"unknown camera(s) {bad}; valid: {list(CAMERAS)}")
    if width < 16 or height < 16 or width % 2 or height % 2:
        raise VideoError(f"width and height must be even and at least 16 (H.264), got "
                         f"{width}x{height}")
    if not fps > 0:
        raise VideoError(f"fps must be positive, got {fps}")
    if every < 1:
        raise VideoError(f"--every must be >= 1, got {every}")
    if max_steps is not None and max_steps < 1:
        raise VideoError(f"--max-steps must be >= 1, got {max_steps}")
    if not 0 <= crf <= 51:
        raise VideoError(f"crf must be in [0, 51] (H.264), got {crf}")


class Mp4Writer:
    """H.264 MP4 (yuv420p, `crf` quality: 18 near lossless .. 28 small), frames (H, W, 3) uint8."""

    def __init__(self, path: str, width: int, height: int, fps: float, crf: int = 23):
        if width % 2 or height % 2:
            raise VideoError(f"H.264 needs an even width and height, got {width}x{height}")
        ff = _ffmpeg()
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        self.path, self.size, self.frames = path, (width, height), 0
        with warnings.catch_warnings():   # JAX warns about any fork; ffmpeg execs at once
            warnings.simplefilter("ignore", RuntimeWarning)
            self._gen = ff.write_frames(
                path, (width, height), fps=fps, codec="libx264", pix_fmt_in="rgb24",
                pix_fmt_out="yuv420p", macro_block_size=2, quality=None, ffmpeg_log_level="error",
                output_params=["-crf", str(int(crf)), "-preset", "medium", "-movflags",
                               "+faststart"])
            self._gen.send(None)

    def write(self, frame: np.ndarray) -> None:
        w, h = self.size
        if frame.shape != (h, w, 3):
            raise ValueError(f"frame of shape {frame.shape}, expected {(h, w, 3)}")
        self._gen.send(np.ascontiguousarray(frame, dtype=np.uint8))
        self.frames += 1

    def close(self) -> None:
        if self._gen is not None:
            self._gen.close()
            self._gen = None


def read_mp4(path: str) -> Tuple[np.ndarray, float]:
    """(frames (n, H, W, 3) uint8, fps) of an MP4 file (for checks; loads it whole)."""
    ff = _ffmpeg()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        gen = ff.read_frames(path)
        meta = gen.__next__()
    w, h = meta["size"]
    frames = [np.frombuffer(b, np.uint8).reshape(h, w, 3) for b in gen]
    return np.stack(frames) if frames else np.zeros((0, h, w, 3), np.uint8), float(meta["fps"])


# ------------------------------------------------------------------------------------------------
# Episodes (host side)
# ------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class Episode:
    """One recorded episode, frame t = the state after t steps (t = 0 .. steps)."""

    xy: np.ndarray                 # (steps + 1, 2)
    option: np.ndarray             # (steps + 1,) option running at frame t (the last repeats)
    subgoal: np.ndarray            # (steps + 1, 2) its subgoal
    qpos: Optional[np.ndarray]     # (steps + 1, nq) MuJoCo qpos (MJX envs), else None
    success: bool
    steps: int


def episodes_from_result(result) -> List[Episode]:
    """Host-side episodes of an EvalResult recorded with `record=True`."""
    if result.obs_seq is None or result.subgoal_seq is None:
        raise ValueError("the EvalResult holds no per-step record: evaluate with record=True")
    obs = np.asarray(result.obs_seq)
    sub = np.asarray(result.subgoal_seq)
    opt = np.asarray(result.option)
    qpos = None if result.qpos_seq is None else np.asarray(result.qpos_seq)
    steps = np.asarray(result.steps)
    succ = np.asarray(result.success)
    out = []
    for e in range(obs.shape[1]):
        n = int(steps[e])
        idx = np.minimum(np.arange(n + 1), max(n - 1, 0))   # frame t shows step t's option
        out.append(Episode(xy=obs[:n + 1, e, :2].astype(np.float64), option=opt[idx, e],
                           subgoal=sub[idx, e].astype(np.float64),
                           qpos=None if qpos is None else qpos[:n + 1, e].astype(np.float64),
                           success=bool(succ[e]), steps=n))
    return out


def frame_indices(steps: int, every: int = 1) -> List[int]:
    """Steps drawn for an episode of `steps` steps: every `every`-th, and always the last."""
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    idx = list(range(0, steps + 1, every))
    if idx[-1] != steps:
        idx.append(steps)
    return idx


def num_frames(steps: Sequence[int], every: int = 1, hold: int = 0) -> int:
    """Frames of a video of episodes of these lengths (each last frame held `hold` extra frames)."""
    return sum(len(frame_indices(int(s), every)) + hold for s in steps)


# ------------------------------------------------------------------------------------------------
# Scene
# ------------------------------------------------------------------------------------------------
def point_mjcf(layout, radius: float, wall_height: float = 1.0) -> str:
    """A draw-only MJCF of a point-mass maze: floor, the layout's wall boxes, a mocap ball."""
    hz = wall_height / 2.0
    walls = "\n".join(
        f'    <geom name="wall_{k}" type="box" pos="{cx:g} {cy:g} {hz:g}" '
        f'size="{hx:g} {hy:g} {hz:g}" rgba="{WALL_RGBA}"/>'
        for k, (cx, cy, hx, hy) in enumerate(layout.wall_boxes))
    size = max(abs(v) for v in layout.bounds) + 10.0
    x, y = layout.start_xy
    return f"""<mujoco model="point_{layout.name}_draw">
  <visual><global offwidth="1280" offheight="1280"/></visual>
  <worldbody>
    <light directional="true" diffuse="1 1 1" pos="0 0 10" dir="0 0 -1"/>
    <geom name="floor" type="plane" size="{size:g} {size:g} 1" rgba="{FLOOR_RGBA}"/>
{walls}
    <body name="point" mocap="true" pos="{x:g} {y:g} {radius:g}">
      <geom name="point_geom" type="sphere" size="{radius:g}" rgba="0.2 0.2 0.8 1"/>
    </body>
  </worldbody>
</mujoco>
"""


class MazeScene:
    """MuJoCo model + data of an env for drawing, and what the markers need to know."""

    def __init__(self, env):
        self.env = env
        self.layout = env.layout
        self.goal = np.asarray(env.goal, np.float64)
        self.goal_tolerance = float(env.goal_tolerance)
        self.is_mjx = getattr(env, "mj_model", None) is not None
        if self.is_mjx:
            # a private copy: the renderer widens the offscreen buffer of its model
            self.model = mujoco.MjModel.from_xml_string(env.xml)
            self.agent_geom = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "torso_geom")
            self.agent_radius = 0.25
            self.halo_radius = 0.7
            self.follow_distance, self.follow_height = 5.0, 0.5
        else:
            self.agent_radius = max(0.08 * self.layout.cell_size, float(env.config.radius))
            self.model = mujoco.MjModel.from_xml_string(point_mjcf(self.layout, self.agent_radius))
            self.agent_geom = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "point_geom")
            self.halo_radius = 1.6 * self.agent_radius
            self.follow_distance = 2.5 * self.layout.cell_size
            self.follow_height = 0.0
        _soften_lights(self.model)
        self.data = mujoco.MjData(self.model)
        # goal ball radius (subgoal ball, start disc: 0.6x): visible in a top view of a big maze
        self.marker_radius = max(0.3, 0.12 * self.layout.cell_size)
        self.wall_height = 1.0 if not self.is_mjx else float(env.config.wall_height)
        # drawn walls (the ant's invisible proxies excluded): see-through in the following view
        self.wall_geoms = {g for g in range(self.model.ngeom)
                           if (mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_GEOM, g) or "")
                           .startswith("wall_") and self.model.geom_rgba[g, 3] > 0}

    def set_state(self, ep: Episode, t: int) -> None:
        """Pose the model as at frame t of `ep` (kinematics only)."""
        if self.is_mjx:
            if ep.qpos is None:
                raise ValueError("an MJX env's episode needs qpos: evaluate with record=True")
            self.data.qpos[:] = ep.qpos[t]
            self.data.qvel[:] = 0.0
        else:
            self.data.mocap_pos[0] = (ep.xy[t, 0], ep.xy[t, 1], self.agent_radius)
        mujoco.mj_forward(self.model, self.data)

    def agent_xyz(self) -> np.ndarray:
        return np.array(self.data.geom_xpos[self.agent_geom])


def _soften_lights(model) -> None:
    """The MJCFs' overhead light plus MuJoCo's headlight wash a top view out to white."""
    model.light_diffuse[:] = 0.4
    model.light_ambient[:] = 0.1
    model.light_specular[:] = 0.1
    model.vis.headlight.ambient[:] = 0.15
    model.vis.headlight.diffuse[:] = 0.25
    model.vis.headlight.specular[:] = 0.0
    model.vis.quality.shadowsize = 2048


def topdown_camera(layout, width: int, height: int, fovy_deg: float = 45.0,
                   wall_height: float = 2.0, margin: float = 1.04):
    """A free camera straight above the maze centre that sees the whole map (x right, y up)."""
    xmin, xmax, ymin, ymax = layout.bounds
    half = max((ymax - ymin) / 2.0, (xmax - xmin) / 2.0 * height / width) * margin
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = ((xmin + xmax) / 2.0, (ymin + ymax) / 2.0, 0.0)
    # the wall tops are `wall_height` nearer than the floor: fit them
    cam.distance = half / np.tan(np.radians(fovy_deg) / 2.0) + wall_height
    cam.azimuth, cam.elevation = 90.0, -90.0
    return cam


def follow_camera(xyz, distance: float, height: float = 0.5, azimuth: float = 90.0,
                  elevation: float = -60.0):
    """A free camera looking at `xyz` from behind (-y side) and above."""
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = (float(xyz[0]), float(xyz[1]), height)
    cam.distance, cam.azimuth, cam.elevation = distance, azimuth, elevation
    return cam


def _add_geom(scene, gtype, size, pos, rgba, emission: float = 0.0) -> None:
    if scene.ngeom >= scene.maxgeom:
        return
    g = scene.geoms[scene.ngeom]
    mujoco.mjv_initGeom(g, gtype, np.asarray(size, np.float64), np.asarray(pos, np.float64),
                        np.eye(3).ravel(), np.asarray(rgba, np.float32))
    g.emission = emission
    g.category = mujoco.mjtCatBit.mjCAT_DECOR
    scene.ngeom += 1


def _add_line(scene, a, b, rgba, width: float = 3.0) -> None:
    if scene.ngeom >= scene.maxgeom:
        return
    g = scene.geoms[scene.ngeom]
    mujoco.mjv_initGeom(g, mujoco.mjtGeom.mjGEOM_LINE, np.zeros(3), np.zeros(3), np.eye(3).ravel(),
                        np.asarray(rgba, np.float32))
    mujoco.mjv_connector(g, mujoco.mjtGeom.mjGEOM_LINE, width, np.asarray(a, np.float64),
                         np.asarray(b, np.float64))
    g.category = mujoco.mjtCatBit.mjCAT_DECOR
    scene.ngeom += 1


def draw_markers(scene, ms: MazeScene, ep: Episode, t: int, colors: Dict[int, tuple],
                 wall_alpha: float = 1.0) -> None:
    """Add the goal, start, path, option halo and subgoal to a scene after `update_scene`, colour
    the agent by its option, and give the walls `wall_alpha` (below 1: see-through)."""
    disc, ball = mujoco.mjtGeom.mjGEOM_CYLINDER, mujoco.mjtGeom.mjGEOM_SPHERE
    tol = ms.goal_tolerance
    gx, gy = ms.goal
    big = ms.marker_radius
    _add_geom(scene, disc, (tol, 0, 0.01), (gx, gy, 0.01), GOAL_RGBA[:3] + (0.6,))
    _add_geom(scene, ball, (big, 0, 0), (gx, gy, big + 0.05), GOAL_RGBA, emission=0.3)
    sx, sy = ep.xy[0]
    _add_geom(scene, disc, (0.6 * big, 0, 0.01), (sx, sy, 0.012), START_RGBA[:3] + (0.8,))
    # path so far, coloured by option
    stride = max(1, -(-t // MAX_TRAIL))
    pts = list(range(0, t, stride)) + [t]
    for a, b in zip(pts[:-1], pts[1:]):
        _add_line(scene, (*ep.xy[a], 0.05), (*ep.xy[b], 0.05), colors[int(ep.option[a])])
    rgba = colors[int(ep.option[t])]
    x, y = ep.xy[t]
    _add_geom(scene, disc, (ms.halo_radius, 0, 0.01), (x, y, 0.02), rgba[:3] + (0.55,))
    sgx, sgy = ep.subgoal[t]
    _add_geom(scene, disc, (tol, 0, 0.01), (sgx, sgy, 0.015), rgba[:3] + (0.25,))
    _add_geom(scene, ball, (0.6 * big, 0, 0), (sgx, sgy, 0.3), rgba, emission=0.3)
    _add_line(scene, (x, y, 0.3), (sgx, sgy, 0.3), rgba[:3] + (0.8,), width=2.0)
    for i in range(scene.ngeom):   # colour the agent (torso / point) by option
        g = scene.geoms[i]
        if g.objtype == mujoco.mjtObj.mjOBJ_GEOM:
            if g.objid == ms.agent_geom:
                g.rgba[:] = rgba
            elif wall_alpha < 1.0 and g.objid in ms.wall_geoms:
                g.rgba[3] = wall_alpha


def option_colors(max_options: int) -> Dict[int, tuple]:
    """RGBA of every option index (and -1: none) as in the trajectory plots."""
    return {k: option_color(k, max_options) for k in range(-1, max_options)}


def render_episodes(env, episodes: Sequence[Episode], out_dir: str, max_options: int,
                    cameras: Iterable[str] = CAMERAS, width: int = 480, height: int = 480,
                    fps: float = 30.0, every: int = 1, hold_s: float = 0.5, crf: int = 23,
                    prefix: str = "eval", shadows: Optional[bool] = None) -> Dict[str, str]:
    """Write `{out_dir}/{prefix}_{camera}.mp4` for each camera; returns {camera: path}.

    `shadows`: None draws shadows unless OpenGL runs in software (then a frame costs ~20x)."""
    cameras = list(dict.fromkeys(cameras))
    check_options(cameras, width, height, fps, every, None, crf)
    if not episodes:
        raise ValueError("no episodes to render")
    ms = MazeScene(env)
    renderer = _renderer(ms.model, width, height)
    if shadows is None:
        shadows = not is_software_gl(renderer)
    colors = option_colors(max_options)
    fovy = float(ms.model.vis.global_.fovy)
    top = topdown_camera(ms.layout, width, height, fovy, ms.wall_height)
    hold = int(round(hold_s * fps))
    writers = {c: Mp4Writer(os.path.join(out_dir, f"{prefix}_{c}.mp4"), width, height, fps, crf)
               for c in cameras}
    try:
        for ep in episodes:
            for t in frame_indices(ep.steps, every):
                ms.set_state(ep, t)
                for c, w in writers.items():
                    cam = top if c == "topdown" else follow_camera(
                        ms.agent_xyz(), ms.follow_distance, ms.follow_height)
                    renderer.update_scene(ms.data, camera=cam)
                    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = bool(shadows)
                    # walls between the following camera and the agent must not hide it
                    draw_markers(renderer.scene, ms, ep, t, colors,
                                 wall_alpha=1.0 if c == "topdown" else 0.4)
                    frame = renderer.render()
                    w.write(frame)
                    for _ in range(hold if t == ep.steps else 0):
                        w.write(frame)
    finally:
        for w in writers.values():
            w.close()
        renderer.close()
    return {c: w.path for c, w in writers.items()}


# ------------------------------------------------------------------------------------------------
# From a run's policy
# ------------------------------------------------------------------------------------------------
def rollout(state, key, num_episodes: int = 1, starts=None, max_steps: Optional[int] = None):
    """Deterministic evaluation episodes with the per-step record (EvalResult)."""
    if starts is not None:
        starts = jnp.asarray(starts, jnp.float32).reshape(-1, 2)
        num_episodes = int(starts.shape[0])
    return evaluate_episodes(state, key, int(num_episodes), starts, record=True,
                             num_steps=None if max_steps is None else int(max_steps))


RECORD_FILE = "episodes.npz"


def save_record(path: str, episodes: Sequence[Episode], meta: dict) -> str:
    """Write recorded episodes and their run's facts (`meta`: env, algo, iteration, ...) to one
    ``.npz``: what `render_record` needs to draw them, on this machine or another."""
    arrays = {"meta": np.array(json.dumps(meta))}
    for i, ep in enumerate(episodes):
        arrays[f"e{i}_xy"] = ep.xy
        arrays[f"e{i}_option"] = ep.option
        arrays[f"e{i}_subgoal"] = ep.subgoal
        arrays[f"e{i}_outcome"] = np.array([int(ep.success), ep.steps])
        if ep.qpos is not None:
            arrays[f"e{i}_qpos"] = ep.qpos
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    np.savez_compressed(path, **arrays)
    return path


def load_record(path: str) -> Tuple[List[Episode], dict]:
    """(episodes, meta) written by `save_record`."""
    try:
        z = np.load(path, allow_pickle=False)
        meta = json.loads(str(z["meta"]))
        n = sum(1 for k in z.files if k.endswith("_outcome"))
        eps = []
        for i in range(n):
            succ, steps = (int(v) for v in z[f"e{i}_outcome"])
            eps.append(Episode(xy=z[f"e{i}_xy"], option=z[f"e{i}_option"],
                               subgoal=z[f"e{i}_subgoal"],
                               qpos=z[f"e{i}_qpos"] if f"e{i}_qpos" in z.files else None,
                               success=bool(succ), steps=steps))
    except (OSError, KeyError, ValueError) as e:
        raise ValueError(f"{path} is not a recording of evaluation episodes ({e}); write one "
                         f"with `video --run RUN --record-only`") from None
    if not eps:
        raise ValueError(f"{path} holds no episodes")
    return eps, meta


def record_run(cfg, state, episodes: int = 1, starts=None, seed: int = 0,
               max_steps: Optional[int] = None) -> Tuple[List[Episode], dict]:
    """Roll out a run's policy (no rendering): the episodes and the facts `render_record` needs."""
    res = rollout(state, jax.random.PRNGKey(seed), episodes, starts, max_steps)
    meta = {"env": cfg.env, "algo": cfg.algo, "iteration": int(state.counters.iteration),
            "env_steps": int(state.counters.env_steps), "seed": seed,
            "max_options": int(cfg.chain.max_options)}
    return episodes_from_result(res), meta


def render_record(cfg, episodes: Sequence[Episode], meta: dict, out_dir: str,
                  cameras: Iterable[str] = CAMERAS, width: int = 480, height: int = 480,
                  fps: float = 30.0, every: int = 1, hold_s: float = 0.5,
                  crf: int = 23) -> Dict[str, str]:
    """Draw recorded episodes of the run configured by `cfg`; write the videos and
    `eval_video.json` under `out_dir`. Returns {camera: path, "summary": path}."""
    check_options(cameras, width, height, fps, every, None, crf)
    select_gl_backend()
    _ffmpeg()
    env = T.make_env(cfg)
    t0 = time.time()
    paths = render_episodes(env, episodes, out_dir, int(meta["max_options"]), cameras, width,
                            height, fps, every, hold_s, crf)
    render_s = time.time() - t0
    colors = option_colors(int(meta["max_options"]))
    hold = int(round(hold_s * fps))
    used = sorted({int(o) for ep in episodes for o in ep.option})
    frame0 = 0
    ep_info = []
    for ep in episodes:
        n = len(frame_indices(ep.steps, every)) + hold
        ep_info.append({"start_xy": [float(v) for v in ep.xy[0]], "success": bool(ep.success),
                        "steps": int(ep.steps), "first_frame": frame0, "frames": n,
                        "options": sorted({int(o) for o in ep.option})})
        frame0 += n
    summary = {
        "env": meta["env"], "algo": meta["algo"], "iteration": meta["iteration"],
        "env_steps": meta["env_steps"], "seed": meta["seed"], "gl_backend": select_gl_backend(),
        "fps": fps, "every": every, "width": width, "height": height, "frames": frame0,
        "files": {c: os.path.basename(p) for c, p in paths.items()}, "episodes": ep_info,
        "option_colors": {str(k): _hex(colors[k]) for k in used},
        "goal_color": _hex(GOAL_RGBA), "render_seconds": round(render_s, 2),
    }
    spath = os.path.join(out_dir, "eval_video.json")
    with open(spath, "w") as f:
        json.dump(summary, f, indent=2)
    return dict(paths, summary=spath)


def render_run(cfg, state, out_dir: str, episodes: int = 1, starts=None, seed: int = 0,
               cameras: Iterable[str] = CAMERAS, width: int = 480, height: int = 480,
               fps: float = 30.0, every: int = 1, max_steps: Optional[int] = None,
               hold_s: float = 0.5, crf: int = 23) -> Dict[str, str]:
    """Roll out a run's policy and write the videos and `eval_video.json` under `out_dir`.

    Returns {camera: path, "summary": path}."""
    check_options(cameras, width, height, fps, every, max_steps, crf)
    select_gl_backend()   # fail before the rollout compiles when nothing can render
    _ffmpeg()
    eps, meta = record_run(cfg, state, episodes, starts, seed, max_steps)
    return render_record(cfg, eps, meta, out_dir, cameras, width, height, fps, every, hold_s, crf)


def _hex(rgba) -> str:
    return "#" + "".join(f"{int(round(255 * float(c))):02x}" for c in rgba[:3])
