"""The MJX ant mazes: jit+vmap on every layout, MJX vs MuJoCo C, walls hold, determinism, NaNs.

One jitted, vmapped rollout (reset_at + lax.scan of steps) per layout, with one shape everywhere,
so each layout compiles once; MuJoCo C is the oracle.
"""
import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from dscpp_jax import envs
from dscpp_jax.envs.ant_maze import body_points, warp_available

B, T = 4, 25  # envs per batch, env steps per rollout (>= 20 for the MJX-vs-C check)
# Penetration allowed for points on the centre lines of the ant's capsules / sphere centres
# (soft contacts give a few cm under a hard shove; a leg passing through would be > 0.3).
WALL_TOL = 0.1
FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


@functools.lru_cache(maxsize=None)
def get_env(name, physics="jax"):
    return envs.make(name, physics=physics, warp_worlds=B)


@functools.lru_cache(maxsize=None)
def rollout_fn(name, physics="jax"):
    env = get_env(name, physics)

    def one(key, xy, vel, actions):
        s = env.reset_at(key, xy)
        d = s.pipeline_state
        s = s.replace(pipeline_state=d.replace(qvel=d.qvel.at[:2].set(vel)))
        s = s.replace(obs=s.obs.at[15:17].set(vel))

        def f(s, a):
            s = env.step(s, a)
            d = s.pipeline_state
            return s, dict(obs=s.obs, reward=s.reward, done=s.done, xpos=d.geom_xpos, xmat=d.geom_xmat,
                           overflow=s.info["overflow"])
        s1, out = jax.lax.scan(f, s, actions)
        out["qpos0"], out["qvel0"] = d.qpos, s.pipeline_state.qvel
        return out

    return jax.jit(jax.vmap(one), compiler_options=FAST_COMPILE)


def rollout(name, key, xy, vel, actions, physics="jax"):
    out = rollout_fn(name, physics)(jax.random.split(key, B), jnp.asarray(xy, jnp.float32),
                           jnp.asarray(vel, jnp.float32), jnp.asarray(actions, jnp.float32))
    return jax.tree.map(np.asarray, out)


def random_actions(seed):
    return np.random.default_rng(seed).uniform(-1, 1, (B, T, 8))


def wall_depth(layout, pts):
    """Penetration depth (> 0 inside) of (..., 2) points into the wall boxes; NumPy."""
    boxes = np.asarray(layout.wall_boxes)
    dx = boxes[:, 2] - np.abs(pts[..., None, 0] - boxes[:, 0])
    dy = boxes[:, 3] - np.abs(pts[..., None, 1] - boxes[:, 1])
    return np.max(np.minimum(dx, dy), axis=-1)


def max_penetration(env, xpos, xmat):
    pts = body_points(env.mj_model, xpos, xmat.reshape(xpos.shape[:-1] + (3, 3)))
    below = pts[..., 2] < env.config.wall_height
    return float(np.max(np.where(below, wall_depth(env.layout, pts[..., :2]), -np.inf)))


@pytest.mark.parametrize("name", list(envs.ANT_NAMES))
def test_every_layout_resets_and_steps_jit_vmap(name):
    env = get_env(name)
    start = np.broadcast_to(np.asarray(env.layout.start_xy), (B, 2))
    out = rollout(name, jax.random.key(0), start, np.zeros((B, 2)), random_actions(0))
    assert out["obs"].shape == (B, T, 29)
    assert np.all(np.isfinite(out["obs"]))
    # Starts at the task start (reset noise U(-0.1, 0.1)), ant stays upright-ish and nearby.
    assert np.all(np.abs(out["qpos0"][:, :2] - start) <= 0.1 + 1e-6)
    assert np.all(np.abs(out["obs"][:, -1, :2] - start) < 2.0)
    assert np.all(out["obs"][:, :, 2] > 0.1)  # torso above the floor: feet-floor contacts work
    assert np.all(out["reward"] == -1.0) and np.all(out["done"] == 0.0)
    assert max_penetration(env, out["xpos"], out["xmat"]) < WALL_TOL


def c_rollout(env, qpos0, qvel0, actions):
    m = env.mj_model
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = qpos0, qvel0
    obs = []
    for a in actions:
        env.mujoco_c_step(d, a)
        obs.append(np.concatenate([d.qpos[:15], d.qvel[:14]]))
    return np.array(obs)


def test_mjx_matches_mujoco_c():
    """Same MjModel, same initial state and controls: MJX (float32) tracks MuJoCo C (float64).

    Tolerance (float32 vs float64; a round-off can flip a contact event, after which one
    trajectory drifts): every env within 1e-4 (torso x, y, z and joint angles) over the first 10
    env steps and within 0.03 over 20 steps (100 physics steps with floor contacts); most envs
    within 1e-3 over 20 steps. The joints move by > 0.2 rad.
    """
    env = get_env("u_maze")
    acts = random_actions(1)
    out = rollout("u_maze", jax.random.key(1), np.zeros((B, 2)), np.zeros((B, 2)), acts)
    close = 0
    for b in range(B):
        ref = c_rollout(env, out["qpos0"][b], out["qvel0"][b], acts[b])
        mjx_obs = out["obs"][b]
        err = np.abs(mjx_obs - ref)[:, np.r_[0:3, 7:15]]
        assert err[:10].max() < 1e-4
        assert err[:20].max() < 0.03
        close += err[:20].max() < 1e-3
        assert np.max(np.abs(ref[:, 7:15] - ref[0, 7:15])) > 0.2  # the joints did move
    assert close >= B - 1


@pytest.mark.skipif(not warp_available(), reason="warp-lang is not installed")
def test_warp_matches_mujoco_c():
    """MuJoCo Warp (through MJX) on the same model, initial state and controls tracks MuJoCo C
    as MJX-JAX does (it runs on the CPU too, slowly), never overflows its contact buffers, and
    keeps its contact arrays shared by the batch (not batched per env)."""
    env = get_env("u_maze", "warp")
    acts = random_actions(1)
    out = rollout("u_maze", jax.random.key(1), np.zeros((B, 2)), np.zeros((B, 2)), acts, "warp")
    close = 0
    for b in range(B):
        ref = c_rollout(env, out["qpos0"][b], out["qvel0"][b], acts[b])
        err = np.abs(out["obs"][b] - ref)[:, np.r_[0:3, 7:15]]
        assert err[:10].max() < 1e-4
        assert err[:20].max() < 0.05
        close += err[:20].max() < 1e-3
    assert close >= B - 2
    assert not np.any(out["overflow"])
    s = jax.vmap(env.reset)(jax.random.split(jax.random.key(0), B))
    assert s.pipeline_state.qpos.shape == (B, 15)
    assert s.pipeline_state._impl.contact__dist.shape == (env.naconmax,)


_TEMPLATE_DIGEST = """
import hashlib, jax, numpy as np
from dscpp_jax import envs
env = envs.make("u_maze", physics="warp", warp_worlds=4)
h = hashlib.sha256()
for leaf in jax.tree_util.tree_leaves((env._data0, env.mjx_model)):
    if hasattr(leaf, "shape"):
        h.update(np.asarray(leaf).tobytes())
print("DIGEST", h.hexdigest())
"""


@pytest.mark.skipif(not warp_available(), reason="warp-lang is not installed")
def test_warp_template_is_the_same_in_every_process():
    """The Warp model and data template are baked into `init`'s program as constants, so any
    byte that differs between processes (MuJoCo Warp's put_data leaves one buffer unset) changes
    the program's persistent-cache key and makes every warm start compile `init` again."""
    import os
    import subprocess
    import sys
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=root)
    digests = []
    for _ in range(2):
        out = subprocess.run([sys.executable, "-c", _TEMPLATE_DIGEST], capture_output=True,
                             text=True, env=env, cwd=root, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        digests.append([ln for ln in out.stdout.splitlines() if ln.startswith("DIGEST")][0])
    assert digests[0] == digests[1]
    impl = get_env("u_maze", "warp")._data0._impl
    assert not np.any(np.asarray(impl.contact__geomcollisionid))


def test_warp_contact_overflow_is_reported():
    """Buffers sized for fewer worlds than are stepped: the dropped contacts are reported."""
    if not warp_available():
        pytest.skip("warp-lang is not installed")
    env = envs.make("u_maze", physics="warp", warp_worlds=1, warp_contacts_per_world=1)
    s = jax.vmap(env.reset)(jax.random.split(jax.random.key(0), B))
    step = jax.jit(jax.vmap(env.step), compiler_options=FAST_COMPILE)
    for _ in range(3):   # the ant drops onto its feet: 4 worlds x up to 5 floor contacts
        s = step(s, jnp.zeros((B, 8)))
    assert np.all(np.asarray(s.info["overflow"]) == 1.0)


def test_physics_choice_is_checked():
    with pytest.raises(ValueError, match="physics must be"):
        envs.make("u_maze", physics="bullet")


@pytest.mark.parametrize("name", ["u_maze", "four_rooms"])
def test_walls_hold_mjx(name):
    """Ants started next to walls and thrown at them (3 m/s) with bang-bang / random torques."""
    env = get_env(name)
    L = env.layout
    S = L.cell_size
    # Free cells with a wall on the +x / -y side: start 0.35 S from that face, velocity into it.
    wall = L.wall_grid()
    xy, vel = [], []
    for (x, y) in L.free_cells:
        j = int(round(x / S)) + L.origin[1]
        i = int(round(y / S)) + L.origin[0]
        if wall[i, j + 1]:
            xy.append((x + 0.15 * S, y)), vel.append((3.0, 0.0))
        elif wall[i - 1, j]:
            xy.append((x, y - 0.15 * S)), vel.append((0.0, -3.0))
        if len(xy) == B:
            break
    acts = np.sign(random_actions(2))
    acts[::2] = np.sign(np.sin(np.arange(T)[:, None] * 0.8 + np.arange(8)))  # rhythmic flailing
    out = rollout(name, jax.random.key(2), xy, vel, acts)
    assert np.all(np.isfinite(out["obs"]))
    assert max_penetration(env, out["xpos"], out["xmat"]) < WALL_TOL
    # They did hit the wall: the torso reached the face (within torso radius + 0.2).
    face_gap = [np.min(np.abs(wall_depth(L, out["obs"][b, :, :2]))) for b in range(len(xy))]
    assert min(face_gap) < 0.45


@pytest.mark.parametrize("name,wall_mode", [("u_maze", "proxy"), ("u_maze", "static"),
                                            ("four_rooms", "proxy"), ("ant_reacher", "proxy")])
def test_walls_hold_mujoco_c_long_push(name, wall_mode):
    """Same MjModel in MuJoCo C (the MJX test above checks MJX follows it): 6 episodes x 200 env
    steps, torso shoved by an external 5 N force in a random direction under random/bang-bang
    torques; no ant body point goes deeper than WALL_TOL into a wall (proxy and static walls)."""
    env = envs.make(name, wall_mode=wall_mode)
    m = env.mj_model
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    worst = -np.inf
    torso = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "torso")
    touched = 0
    for ep in range(6):
        mujoco.mj_resetData(m, d)
        d.qpos[:2] = env.layout.free_cells[rng.integers(len(env.layout.free_cells))]
        direction = rng.normal(size=2)
        direction /= np.linalg.norm(direction)
        for k in range(200):
            a = rng.uniform(-1, 1, 8) if ep % 2 else np.sign(np.sin(0.5 * k + np.arange(8)))
            d.xfrc_applied[torso, :2] = 5.0 * direction
            env.mujoco_c_step(d, a)
            pts = body_points(m, d.geom_xpos, d.geom_xmat.reshape(-1, 3, 3))
            pts = pts[pts[:, 2] < env.config.wall_height]
            worst = max(worst, wall_depth(env.layout, pts[:, :2]).max())
        touched += wall_depth(env.layout, d.qpos[None, :2])[0] > -0.6
    assert worst < WALL_TOL, worst
    assert touched >= 2  # episodes ended pressed against a wall


def test_same_key_same_trajectory_and_reset_noise():
    acts = random_actions(3)
    a = rollout("u_maze", jax.random.key(7), np.zeros((B, 2)), np.zeros((B, 2)), acts)
    b = rollout("u_maze", jax.random.key(7), np.zeros((B, 2)), np.zeros((B, 2)), acts)
    c = rollout("u_maze", jax.random.key(8), np.zeros((B, 2)), np.zeros((B, 2)), acts)
    np.testing.assert_array_equal(a["obs"], b["obs"])
    assert not np.allclose(a["obs"], c["obs"])
    # D4RL reset noise: qpos within +-0.1 of qpos0 (quaternion renormalised), qvel ~ 0.1 N(0, 1).
    env = get_env("u_maze")
    q0 = env.mj_model.qpos0.copy()
    dq = a["qpos0"] - q0
    assert np.all(np.abs(dq[:, np.r_[0:3, 7:15]]) <= 0.1 + 1e-6)
    assert 0.02 < np.std(a["qvel0"][:, 2:]) < 0.3


def test_success_nan_and_goal_override():
    env = get_env("u_maze")
    s = env.reset_at(jax.random.key(0), jnp.array([0.0, 7.8]))
    step = jax.jit(env.step, compiler_options=FAST_COMPILE)
    s1 = step(s, jnp.zeros(8))
    assert float(s1.reward) == 0.0 and float(s1.done) == 1.0 and float(s1.info["success"]) == 1.0
    # A subgoal replaces the task goal for reward/termination.
    s2 = step(s.replace(info=dict(s.info, goal=jnp.array([8.0, 8.0]))), jnp.zeros(8))
    assert float(s2.reward) == -1.0 and float(s2.done) == 0.0
    # NaN physics: episode ends, reward 0, last finite observation kept.
    d = s.pipeline_state
    bad = s.replace(pipeline_state=d.replace(qvel=d.qvel.at[6].set(jnp.nan)))
    s3 = step(bad, jnp.zeros(8))
    assert float(s3.info["nan"]) == 1.0 and float(s3.done) == 1.0 and float(s3.reward) == 0.0
    np.testing.assert_array_equal(np.asarray(s3.obs), np.asarray(s.obs))
    # Diverse starts for the ant keep the torso out of walls.
    xy = jax.vmap(env.sample_start)(jax.random.split(jax.random.key(1), 256))
    assert not np.any(np.asarray(env.layout.in_wall(xy, env.config.start_margin * 0.99)))


def test_upright_matches_mujoco_torso_rotation():
    # oracle: MuJoCo C's torso rotation matrix, z-axis world z component (xmat[2, 2])
    env = get_env("u_maze")
    m = env.mj_model
    d = mujoco.MjData(m)
    torso = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "torso")
    rng = np.random.default_rng(0)
    for _ in range(5):
        q = rng.normal(size=4)
        d.qpos[:] = m.qpos0
        d.qpos[3:7] = q / np.linalg.norm(q)
        mujoco.mj_forward(m, d)
        obs = np.concatenate([d.qpos[:15], d.qvel[:14]])
        np.testing.assert_allclose(float(env.upright(obs)), d.xmat[torso].reshape(3, 3)[2, 2],
                                   atol=1e-5)
    d.qpos[:] = m.qpos0
    assert float(env.upright(np.concatenate([d.qpos[:15], d.qvel[:14]]))) == pytest.approx(1.0)
    d.qpos[3:7] = [0.0, 1.0, 0.0, 0.0]            # half a turn about x: on its back
    assert float(env.upright(np.concatenate([d.qpos[:15], d.qvel[:14]]))) == pytest.approx(-1.0)


def test_contacts_follow_d4rl_and_damping_is_implicit():
    # D4RL's ant.xml default geom class: solref ".02 1", solimp ".8 .8 .01"; the margin stays 0
    # (MJX departs from MuJoCo C with one, see AntConfig)
    m = get_env("u_maze").mj_model
    np.testing.assert_allclose(m.geom_solimp[:, :3], np.tile([0.8, 0.8, 0.01], (m.ngeom, 1)))
    np.testing.assert_allclose(m.geom_solref, np.tile([0.02, 1.0], (m.ngeom, 1)))
    assert np.all(m.geom_margin == 0.0)
    assert not m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_EULERDAMP
    stiff = envs.make("u_maze", contact_solimp="0.9 0.95 0.001", eulerdamp=False).mj_model
    np.testing.assert_allclose(stiff.geom_solimp[:, :3], np.tile([0.9, 0.95, 0.001], (m.ngeom, 1)))
    assert stiff.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_EULERDAMP
