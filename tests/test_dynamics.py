"""Dynamics ensemble: normaliser, prediction algebra, fitting point-mass and ant transitions."""
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dscpp_jax import envs
from dscpp_jax.dynamics import (DynamicsConfig, dynamics_fit_normaliser, dynamics_fold, dynamics_init,
                                dynamics_metrics, dynamics_predict, dynamics_predict_all, dynamics_train,
                                dynamics_update, folded_step)


def _np_mlp(params, x, slope=0.01):
    """Plain NumPy forward of one member's flax params."""
    p = params["params"]
    n = len(p)
    for i in range(n):
        x = x @ np.asarray(p[f"Dense_{i}"]["kernel"]) + np.asarray(p[f"Dense_{i}"]["bias"])
        if i < n - 1:
            x = np.where(x > 0, x, slope * x)
    return x


def _point_transitions(n, seed=0):
    """Random (obs, action, next_obs) of the true point mass in the open arena."""
    env = envs.make("point_ant_reacher")
    k1, k2, k3 = jax.random.split(jax.random.key(seed), 3)
    xy = jax.random.uniform(k1, (n, 2), minval=-9.0, maxval=9.0)
    vel = jax.random.uniform(k2, (n, 2), minval=-3.0, maxval=3.0)
    obs = jnp.concatenate([xy, vel], -1)
    act = jax.random.uniform(k3, (n, 2), minval=-1.0, maxval=1.0)
    base = env.reset(jax.random.key(0))
    st = jax.vmap(lambda o: base.replace(obs=o))(obs)
    nxt = jax.jit(jax.vmap(env.step))(st, act).obs
    return np.asarray(obs), np.asarray(act), np.asarray(nxt)


def test_normaliser_matches_numpy_masked_stats():
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(6, 5, 3)) * [1.0, 2.0, 0.0] + [0.0, 1.0, 3.0]  # one constant column
    act = rng.uniform(-1, 1, size=(6, 5, 2))
    nxt = obs + rng.normal(size=obs.shape) * 0.1
    mask = rng.uniform(size=(6, 5)) < 0.6
    cfg = DynamicsConfig()
    st = dynamics_fit_normaliser(dynamics_init(jax.random.key(0), 3, 2, cfg), obs, act, nxt, mask, cfg)
    o, a, d = obs[mask], act[mask], (nxt - obs)[mask]
    np.testing.assert_allclose(st.norm.obs_mean, o.mean(0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(st.norm.obs_std, np.maximum(o.std(0), 1e-5), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(st.norm.act_std, a.std(0), rtol=1e-4)
    np.testing.assert_allclose(st.norm.delta_mean, d.mean(0), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(st.norm.delta_std, d.std(0), rtol=1e-4)
    assert float(st.norm.obs_std[2]) == pytest.approx(1e-5)  # constant column floored, never 0
    # No valid row: statistics stay as they were.
    st2 = dynamics_fit_normaliser(st, obs, act, nxt, np.zeros_like(mask), cfg)
    np.testing.assert_array_equal(st2.norm.obs_mean, st.norm.obs_mean)


def test_predict_and_fold_match_numpy_forward():
    cfg = DynamicsConfig(ensemble_size=3, hidden=(16, 8))
    rng = np.random.default_rng(1)
    obs = rng.normal(size=(40, 5)).astype(np.float32)
    act = rng.uniform(-1, 1, size=(40, 2)).astype(np.float32)
    nxt = obs + 0.3 * rng.normal(size=obs.shape).astype(np.float32)
    st = dynamics_fit_normaliser(dynamics_init(jax.random.key(1), 5, 2, cfg), obs, act, nxt, None, cfg)
    n = jax.tree.map(np.asarray, st.norm)
    x = np.concatenate([(obs - n.obs_mean) / n.obs_std, (act - n.act_mean) / n.act_std], -1)
    ref = np.stack([obs + _np_mlp(jax.tree.map(lambda p: np.asarray(p)[e], st.params), x) * n.delta_std
                    + n.delta_mean for e in range(3)])
    np.testing.assert_allclose(dynamics_predict_all(cfg, st, obs, act), ref, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(dynamics_predict(cfg, st, obs, act), ref.mean(0), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(dynamics_predict(cfg, st, obs, act, member=2), ref[2], rtol=1e-4, atol=1e-4)
    members = np.arange(40) % 3
    np.testing.assert_allclose(dynamics_predict(cfg, st, obs, act, member=members),
                               ref[members, np.arange(40)], rtol=1e-4, atol=1e-4)
    fd = dynamics_fold(cfg, st)
    for e in range(3):
        np.testing.assert_allclose(folded_step(fd, obs, act, member=e), ref[e], rtol=1e-4, atol=1e-4)


def test_fits_point_mass_one_step():
    """Paper architecture (2 x 500) fits the point mass: held-out xy error < 0.02 (moves are <= 0.3)."""
    obs, act, nxt = _point_transitions(3000)
    cfg = DynamicsConfig(batch_size=256)
    st = dynamics_init(jax.random.key(0), 4, 2, cfg)
    tr, te = slice(0, 2500), slice(2500, None)
    st = dynamics_fit_normaliser(st, obs[tr], act[tr], nxt[tr], None, cfg)
    before = dynamics_metrics(cfg, st, obs[te], act[te], nxt[te])
    train = jax.jit(dynamics_train, static_argnums=(0, 4))
    st, m = train(cfg, st, (obs[tr], act[tr], nxt[tr]), jax.random.key(1), 400)
    after = dynamics_metrics(cfg, st, obs[te], act[te], nxt[te])
    assert float(m["loss"][-20:].mean()) < 0.05 * float(m["loss"][:5].mean())
    assert float(after["xy_err"]) < 0.02, after
    assert float(after["rel_err"]) < 0.1, after
    assert float(after["rmse"]) < 0.2 * float(before["rmse"])
    # A "no change" predictor is far worse than the model: the test can fail.
    no_change = np.linalg.norm(nxt[te][:, :2] - obs[te][:, :2], axis=-1).mean()
    assert float(after["xy_err"]) < 0.1 * no_change


def _ant_transitions(n_steps, seed=0, frame_skip=5):
    """Random-action ant transitions from MuJoCo C with brax's ant model (29-d obs as the mazes)."""
    mujoco = pytest.importorskip("mujoco")
    import brax

    path = os.path.join(os.path.dirname(brax.__file__), "envs", "assets", "ant.xml")
    model = mujoco.MjModel.from_xml_path(path)
    data = mujoco.MjData(model)
    rng = np.random.default_rng(seed)
    obs, act, nxt = [], [], []

    def ob():
        return np.concatenate([data.qpos[:15], data.qvel[:14]]).astype(np.float32)

    for t in range(n_steps):
        if t % 100 == 0:
            mujoco.mj_resetData(model, data)
            data.qpos[:] += rng.uniform(-0.1, 0.1, model.nq)
            data.qvel[:] += 0.1 * rng.normal(size=model.nv)
            mujoco.mj_forward(model, data)
        o = ob()
        a = rng.uniform(-1, 1, model.nu)
        data.ctrl[:] = a
        for _ in range(frame_skip):
            mujoco.mj_step(model, data)
        obs.append(o), act.append(a.astype(np.float32)), nxt.append(ob())
    return np.stack(obs), np.stack(act), np.stack(nxt)


def test_heldout_error_falls_on_ant_transitions():
    obs, act, nxt = _ant_transitions(800)
    assert obs.shape == (800, 29) and act.shape == (800, 8)
    tr, te = slice(0, 600), slice(600, None)  # held-out = later episodes
    cfg = DynamicsConfig(batch_size=256)
    st = dynamics_init(jax.random.key(0), 29, 8, cfg)
    st = dynamics_fit_normaliser(st, obs[tr], act[tr], nxt[tr], None, cfg)
    train = jax.jit(dynamics_train, static_argnums=(0, 4))
    errs = [float(dynamics_metrics(cfg, st, obs[te], act[te], nxt[te])["mse_std"])]
    for i in range(3):
        st, _ = train(cfg, st, (obs[tr], act[tr], nxt[tr]), jax.random.key(i), 100)
        errs.append(float(dynamics_metrics(cfg, st, obs[te], act[te], nxt[te])["mse_std"]))
    assert errs[-1] < 0.6 * errs[0], errs
    assert errs[-1] < 1.0, errs  # better than predicting the mean change (mse_std = 1 by construction)


def test_update_jit_matches_eager_and_no_retrace():
    cfg = DynamicsConfig(ensemble_size=2, hidden=(32, 32), batch_size=64)
    obs, act, nxt = _point_transitions(256, seed=3)
    st = dynamics_fit_normaliser(dynamics_init(jax.random.key(0), 4, 2, cfg), obs, act, nxt, None, cfg)
    batch = (obs[:64], act[:64], nxt[:64])
    traces = []

    def upd(s, b, k):
        traces.append(1)
        return dynamics_update(cfg, s, b, k)

    jupd = jax.jit(upd)
    s_j, m_j = jupd(st, batch, jax.random.key(5))
    with jax.disable_jit():
        s_e, m_e = upd(st, batch, jax.random.key(5))
    for a, b in zip(jax.tree.leaves(s_j.params), jax.tree.leaves(s_e.params)):
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=1e-6)
    np.testing.assert_allclose(m_j["loss"], m_e["loss"], rtol=1e-5)
    n0 = len(traces)
    for i in range(3):
        s_j, _ = jupd(s_j, (obs[64 * i:64 * i + 64], act[64 * i:64 * i + 64], nxt[64 * i:64 * i + 64]),
                      jax.random.key(i))
    assert len(traces) == n0  # no retracing across updates
    # Members train on their own bootstrap resamples: they stay different.
    p = jax.tree.leaves(s_j.params)[0]
    assert not np.allclose(p[0], p[1])


def test_train_uses_only_valid_rows():
    """Rows outside the mask never enter a minibatch: poisoned invalid rows leave the loss finite."""
    cfg = DynamicsConfig(hidden=(16,), batch_size=32)
    obs, act, nxt = _point_transitions(128, seed=4)
    mask = np.arange(128) < 100
    nxt_bad = nxt.copy()
    nxt_bad[~mask] = np.nan
    st = dynamics_fit_normaliser(dynamics_init(jax.random.key(0), 4, 2, cfg), obs, act, nxt_bad, mask, cfg)
    st, m = dynamics_train(cfg, st, (obs, act, nxt_bad, mask), jax.random.key(0), 20)
    assert np.isfinite(np.asarray(m["loss"])).all()
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(st.params))


def test_train_reads_a_replay_ring():
    """dynamics_train takes the device ring replay as is (time-major data + valid mask)."""
    from dscpp_jax.replay import replay_add, replay_init

    cfg = DynamicsConfig(hidden=(16,), batch_size=32)
    obs, act, nxt = _point_transitions(40, seed=5)
    buf = replay_init(dict(obs=obs[0], action=act[0], next_obs=nxt[0]), 64, 4)
    for t in range(10):  # 10 rows of 4 envs; the rest of the ring stays invalid
        sl = slice(4 * t, 4 * t + 4)
        buf = replay_add(buf, dict(obs=obs[sl], action=act[sl], next_obs=nxt[sl]))
    assert int(buf.valid.sum()) == 40
    st = dynamics_init(jax.random.key(0), 4, 2, cfg)
    st = dynamics_fit_normaliser(st, buf.data["obs"], buf.data["action"], buf.data["next_obs"], buf.valid, cfg)
    np.testing.assert_allclose(st.norm.obs_mean, obs.mean(0), rtol=1e-4, atol=1e-5)
    st2, m = dynamics_train(cfg, st, buf, jax.random.key(1), 30)
    assert float(m["loss"][-5:].mean()) < float(m["loss"][:2].mean())
