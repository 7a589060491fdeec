"""Random-shooting MPC: eq. 2 cost against NumPy, rollouts against a NumPy MLP, the fused kernel
(interpreted on the CPU, compiled on a GPU) against the XLA path, the terminal value fused into the kernel against
td3_value, and goal reaching on the point mass."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dscpp_jax import envs
from dscpp_jax.dynamics import DynamicsConfig, dynamics_fit_normaliser, dynamics_init, dynamics_train
from dscpp_jax import mpc as mpc_lib
from dscpp_jax.dynamics import dynamics_fold
from dscpp_jax.mpc import (MPCConfig, mpc_action, mpc_actions, mpc_cost, rollout_xy, sample_action_sequences,
                           sequence_costs, shooting_actions, td3_value_net, value_net_fn)
from dscpp_jax.td3 import TD3Config, td3_init, td3_value

TOL = 0.6
# The Pallas kernel compiles on a GPU; elsewhere it runs in interpret mode.
INTERPRET = jax.default_backend() != "gpu"


def _np_cost(pred_xy, goal, values, gamma=0.95, tol=TOL):
    """Plain NumPy eq. 2 with the original's at-goal rule, one sequence at a time."""
    M, K, _ = pred_xy.shape
    out = np.zeros(M)
    vmax = None if values is None else values.max()
    for i in range(M):
        c = 0.0
        for j in range(K):
            c += gamma ** j * (1.0 if np.linalg.norm(pred_xy[i, j] - goal) > tol else 0.0)
        if values is not None:
            v = vmax if np.linalg.norm(pred_xy[i, -1] - goal) <= tol else values[i]
            c -= gamma ** K * v
        out[i] = c
    return out


def test_cost_matches_numpy_including_at_goal_rule():
    rng = np.random.default_rng(0)
    M, K = 64, 7
    goal = np.array([1.0, -2.0])
    # Random walks that start near the goal so every pattern of near/far steps occurs.
    pred = goal + np.cumsum(rng.normal(scale=0.35, size=(M, K, 2)), axis=1)
    values = rng.normal(size=M) * 5 - 10
    cfg = MPCConfig(num_samples=M, horizon=K)
    got = mpc_cost(cfg, pred, goal, values)
    ref = _np_cost(pred, goal, values)
    at_goal = np.linalg.norm(pred[:, -1] - goal, axis=-1) <= TOL
    assert 0 < at_goal.sum() < M  # both branches of the rule are exercised
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)
    flat = mpc_cost(dataclasses.replace(cfg, use_value=False), pred, goal, values)
    np.testing.assert_allclose(flat, _np_cost(pred, goal, None), rtol=1e-5, atol=1e-6)
    # Batched over environments.
    got2 = mpc_cost(cfg, np.stack([pred, pred[::-1]]), np.stack([goal, goal]), np.stack([values, values[::-1]]))
    np.testing.assert_allclose(got2[1], ref[::-1], rtol=1e-5, atol=1e-5)


def _tiny_model(E=2, seed=0, obs_dim=5, act_dim=2):
    cfg = DynamicsConfig(ensemble_size=E, hidden=(16, 8))
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(100, obs_dim)).astype(np.float32)
    act = rng.uniform(-1, 1, size=(100, act_dim)).astype(np.float32)
    nxt = obs + 0.3 * rng.normal(size=obs.shape).astype(np.float32)
    st = dynamics_fit_normaliser(dynamics_init(jax.random.key(seed), obs_dim, act_dim, cfg), obs, act, nxt, None, cfg)
    return cfg, st


def _np_member_step(st, e, s, a):
    n = jax.tree.map(np.asarray, st.norm)
    p = jax.tree.map(lambda x: np.asarray(x)[e], st.params)["params"]
    x = np.concatenate([(s - n.obs_mean) / n.obs_std, (a - n.act_mean) / n.act_std], -1)
    for i in range(3):
        x = x @ p[f"Dense_{i}"]["kernel"] + p[f"Dense_{i}"]["bias"]
        if i < 2:
            x = np.where(x > 0, x, 0.01 * x)
    return s + x * n.delta_std + n.delta_mean


@pytest.mark.parametrize("mode", ["member", "mean"])
def test_sequence_costs_match_numpy_rollout(mode):
    dcfg, st = _tiny_model(E=2)
    M, K = 40, 4
    cfg = MPCConfig(num_samples=M, horizon=K, compute_dtype="float32", backend="xla", ensemble_mode=mode,
                    block_rows=16)
    obs = np.array([[0.2, -0.1, 0.3, 0.0, 1.0]], np.float32)
    goal = np.array([[0.9, 0.4]], np.float32)
    acts = np.asarray(sample_action_sequences(jax.random.key(3), cfg, 1, 2))
    vf = lambda s, g: -jnp.linalg.norm(s[:, :2] - g, axis=-1) * 3.0 + s[:, 2]
    got = sequence_costs(cfg, dcfg, st, obs, goal, acts, vf)[0]
    # NumPy: member (i // block_rows) % E per sequence, or the mean of members at every step.
    s = np.repeat(obs, M, 0).astype(np.float64)
    xy = np.zeros((M, K, 2))
    member = (np.arange(M) // 16) % 2
    for j in range(K):
        preds = np.stack([_np_member_step(st, e, s, acts[0, :, j]) for e in range(2)])
        s = preds.mean(0) if mode == "mean" else preds[member, np.arange(M)]
        xy[:, j] = s[:, :2]
    v = -np.linalg.norm(s[:, :2] - goal[0], axis=-1) * 3.0 + s[:, 2]
    np.testing.assert_allclose(got, _np_cost(xy, goal[0], v), rtol=1e-4, atol=1e-4)


def test_fused_kernel_matches_xla_bf16():
    """The Pallas kernel (interpreted on the CPU, compiled on a GPU) computes what the XLA bfloat16 path computes."""
    dcfg, st = _tiny_model(E=2, obs_dim=29, act_dim=8)
    cfg = MPCConfig(num_samples=100, horizon=3, compute_dtype="bfloat16", block_rows=32, hidden_chunk=16,
                    out_chunk=16, ensemble_mode="member")
    obs = np.random.default_rng(1).normal(size=(2, 29)).astype(np.float32)
    goal = obs[:, :2] + np.array([[0.5, 0.0], [0.0, -0.8]], np.float32)
    acts = sample_action_sequences(jax.random.key(0), cfg, 2, 8)
    vf = lambda s, g: -jnp.linalg.norm(s[:, :2] - g, axis=-1) + 0.1 * s[:, 3]
    ref = sequence_costs(dataclasses.replace(cfg, backend="xla"), dcfg, st, obs, goal, acts, vf)
    got = sequence_costs(cfg, dcfg, st, obs, goal, acts, vf, interpret=INTERPRET)
    assert float(jnp.std(ref)) > 0.05  # costs differ between sequences
    np.testing.assert_allclose(got, ref, rtol=1e-3, atol=2e-3)
    f32 = sequence_costs(dataclasses.replace(cfg, backend="xla", compute_dtype="float32"), dcfg, st, obs, goal,
                         acts, vf)
    np.testing.assert_allclose(got, f32, atol=0.05)  # bf16 operands stay close to float32


def _point_env():
    return envs.make("point_ant_reacher")


def _true_step_fn(env):
    base = env.reset(jax.random.key(0))

    def step(s, a):
        return jax.vmap(lambda o, u: env.step(base.replace(obs=o), u).obs)(s, a)

    return step


def _oracle_value(s, g):
    """Negative steps-to-go of the point mass at top speed 0.3 per step (ignores velocity)."""
    return -jnp.maximum(jnp.linalg.norm(s[:, :2] - g, axis=-1) - TOL, 0.0) / 0.3


def _run_episode(env, decide, start_xy, goal, steps, key):
    state = env.reset_at(jax.random.key(1), jnp.asarray(start_xy, jnp.float32))
    state = state.replace(info={**state.info, "goal": jnp.asarray(goal, jnp.float32)})

    def body(carry, k):
        st, reached = carry
        a = decide(k, st.obs)
        st = env.step(st, a)
        d = jnp.linalg.norm(st.obs[:2] - goal)
        return (st, reached | (d <= TOL)), d

    (_, reached), d = jax.lax.scan(body, (state, jnp.array(False)), jax.random.split(key, steps))
    return bool(reached), np.asarray(d)


def test_mpc_with_true_dynamics_and_value_reaches_distant_goals():
    env = _point_env()
    step = _true_step_fn(env)
    cfg = MPCConfig(num_samples=500, horizon=7)
    for start, goal in [((-6.0, -6.0), (3.0, 4.0)), ((7.0, -2.0), (-4.0, 5.0))]:
        g = jnp.asarray(goal, jnp.float32)
        decide = lambda k, o: shooting_actions(cfg, step, k, o[None], g[None], 2, _oracle_value)[0]
        reached, d = _run_episode(env, decide, start, g, 70, jax.random.key(0))
        assert reached, d[-5:]


def test_flat_mpc_reaches_a_goal_within_its_horizon_only_with_a_value_beyond():
    env = _point_env()
    step = _true_step_fn(env)
    flat = MPCConfig(num_samples=500, horizon=7, use_value=False)
    g = jnp.asarray([1.2, 0.8], jnp.float32)
    decide = lambda k, o: shooting_actions(flat, step, k, o[None], g[None], 2)[0]
    reached, _ = _run_episode(env, decide, (0.0, 0.0), g, 20, jax.random.key(2))
    assert reached
    # 6 units away the sparse cost is flat over the whole horizon: without V it does not get there.
    far = jnp.asarray([6.0, 0.0], jnp.float32)
    decide = lambda k, o: shooting_actions(flat, step, k, o[None], far[None], 2)[0]
    reached, _ = _run_episode(env, decide, (0.0, 0.0), far, 40, jax.random.key(2))
    assert not reached


def test_mpc_with_learned_model_reaches_goal_in_true_env():
    env = _point_env()
    k1, k2, k3 = jax.random.split(jax.random.key(7), 3)
    n = 3000
    obs = jnp.concatenate([jax.random.uniform(k1, (n, 2), minval=-9, maxval=9),
                           jax.random.uniform(k2, (n, 2), minval=-3, maxval=3)], -1)
    act = jax.random.uniform(k3, (n, 2), minval=-1, maxval=1)
    nxt = _true_step_fn(env)(obs, act)
    dcfg = DynamicsConfig(hidden=(64, 64), batch_size=256)
    st = dynamics_fit_normaliser(dynamics_init(jax.random.key(0), 4, 2, dcfg), obs, act, nxt, None, dcfg)
    st, _ = jax.jit(dynamics_train, static_argnums=(0, 4))(dcfg, st, (obs, act, nxt), jax.random.key(1), 600)
    cfg = MPCConfig(num_samples=500, horizon=7, compute_dtype="float32")
    g = jnp.asarray([2.0, -3.0], jnp.float32)
    decide = lambda k, o: mpc_action(cfg, dcfg, st, k, o, g, _oracle_value)
    reached, d = _run_episode(env, decide, (-3.0, 2.0), g, 60, jax.random.key(3))
    assert reached, d[-5:]


def test_jit_matches_eager_no_retrace_and_single_env_api():
    dcfg, st = _tiny_model(E=1, obs_dim=4)
    cfg = MPCConfig(num_samples=64, horizon=3, compute_dtype="float32", backend="xla")
    obs = jnp.asarray([[0.0, 0.0, 0.1, 0.0], [1.0, 1.0, 0.0, 0.2]], jnp.float32)
    goal = jnp.asarray([[0.5, 0.5], [0.0, 0.0]], jnp.float32)
    traces = []

    def f(s, k, o, g):
        traces.append(1)
        return mpc_actions(cfg, dcfg, s, k, o, g, _oracle_value, return_info=True)

    jf = jax.jit(f)
    a_j, info_j = jf(st, jax.random.key(0), obs, goal)
    with jax.disable_jit():
        a_e, info_e = f(st, jax.random.key(0), obs, goal)
    np.testing.assert_allclose(a_j, a_e, atol=1e-6)
    np.testing.assert_allclose(info_j["cost"], info_e["cost"], rtol=1e-5, atol=1e-5)
    n0 = len(traces)
    for i in range(3):
        jf(st, jax.random.key(i + 1), obs + i, goal)
    assert len(traces) == n0
    assert np.all(np.abs(np.asarray(a_j)) <= 1.0)
    single = mpc_action(cfg, dcfg, st, jax.random.key(0), obs[1], goal[1], _oracle_value)
    np.testing.assert_allclose(single, mpc_actions(cfg, dcfg, st, jax.random.key(0), obs[1:], goal[1:],
                                                   _oracle_value)[0], atol=1e-6)
    with pytest.raises(ValueError, match="value_fn"):
        mpc_actions(cfg, dcfg, st, jax.random.key(0), obs, goal)
    with pytest.raises(ValueError, match="ensemble_mode"):
        MPCConfig(ensemble_mode="median")


def test_fused_kernel_ensemble_mean_matches_xla():
    """Mean-of-members mode inside the kernel equals the XLA mean mode (both bf16 operands)."""
    dcfg, st = _tiny_model(E=3, obs_dim=29, act_dim=8)
    cfg = MPCConfig(num_samples=64, horizon=2, compute_dtype="bfloat16", block_rows=32, hidden_chunk=16,
                    out_chunk=16, ensemble_mode="mean", use_value=False)
    obs = np.random.default_rng(2).normal(size=(1, 29)).astype(np.float32)
    goal = obs[:, :2] + np.array([[0.4, 0.3]], np.float32)
    acts = sample_action_sequences(jax.random.key(1), cfg, 1, 8)
    ref = sequence_costs(dataclasses.replace(cfg, backend="xla"), dcfg, st, obs, goal, acts)
    got = sequence_costs(cfg, dcfg, st, obs, goal, acts, interpret=INTERPRET)
    np.testing.assert_allclose(got, ref, atol=1e-5)
    member = sequence_costs(dataclasses.replace(cfg, backend="xla", ensemble_mode="member"), dcfg, st, obs,
                            goal, acts)
    assert not np.allclose(member, ref)  # the modes differ, so the comparison above can fail


def _small_td3(output_normalisation, seed=5, hidden=(32, 48)):
    """A small TD3 actor + twin critic on the 29-d state; 48 = 3 blocks of 16 (not a power of 2)."""
    tcfg = TD3Config.model_based(hidden=hidden, output_normalisation=output_normalisation)
    st = td3_init(jax.random.key(seed), 29, 2, 8, tcfg)
    # Scale the critic's output layer so V spreads over a few units, as a trained critic's does.
    cp = jax.tree.map(lambda x: x, st.critic_params)
    cp["params"]["heads"]["out"]["kernel"] = cp["params"]["heads"]["out"]["kernel"] * 20.0
    return tcfg, st.replace(critic_params=cp)


@pytest.mark.parametrize("output_normalisation", [False, True])
def test_value_net_fn_is_td3_value(output_normalisation):
    tcfg, st = _small_td3(output_normalisation)
    s = jax.random.normal(jax.random.key(1), (50, 29))
    g = jnp.asarray([0.3, -0.2], jnp.float32)
    got = value_net_fn(td3_value_net(tcfg, st))(s, g)
    np.testing.assert_allclose(got, td3_value(tcfg, st, s, jnp.broadcast_to(g, (50, 2))), rtol=1e-6, atol=1e-6)


def test_fused_value_matches_td3_value_and_numpy():
    """The kernel's in-chip value (actor + twin critic on the final states) equals td3_value on the
    kernel's own final states, and its eq. 2 costs equal the XLA path and the NumPy reference."""
    dcfg, st = _tiny_model(E=1, obs_dim=29, act_dim=8)
    tcfg, ts = _small_td3(output_normalisation=False)
    net = td3_value_net(tcfg, ts)
    cfg = MPCConfig(num_samples=64, horizon=2, block_rows=32, hidden_chunk=16, out_chunk=16, value_chunk=16,
                    value_dtype="float32")
    obs = np.random.default_rng(1).normal(size=(2, 29)).astype(np.float32)
    acts = sample_action_sequences(jax.random.key(0), cfg, 2, 8)
    xy, final_xla = rollout_xy(dataclasses.replace(cfg, backend="xla"), dcfg, st, obs, acts)
    goal = np.asarray(xy[:, 0, -1]) + np.array([0.6, 0.0], np.float32)  # about half end within tolerance

    # Kernel outputs directly: value, at-goal flag against td3_value on the final states.
    fd = dynamics_fold(dcfg, st, jnp.bfloat16)
    acts_k = mpc_lib._to_kernel_layout(cfg, acts, 16, 64)
    fused = mpc_lib._rollout_pallas(cfg, dcfg, fd, jnp.asarray(obs), jnp.asarray(goal), acts_k, interpret=INTERPRET,
                                    value_net=net, want_final=False)
    plain = mpc_lib._rollout_pallas(cfg, dcfg, fd, jnp.asarray(obs), jnp.asarray(goal), acts_k, interpret=INTERPRET)
    final = plain["final"][:, :, :29]
    v_ref = jax.vmap(lambda s, g: td3_value(tcfg, ts, s, jnp.broadcast_to(g, (64, 2))))(final, jnp.asarray(goal))
    assert float(jnp.std(v_ref)) > 0.1
    np.testing.assert_allclose(fused["value"], v_ref, rtol=1e-5, atol=1e-5)
    at_goal = np.linalg.norm(np.asarray(final[..., :2]) - goal[:, None], axis=-1) <= TOL
    assert 0 < at_goal.sum() < at_goal.size
    np.testing.assert_array_equal(fused["at_goal"], at_goal)
    np.testing.assert_allclose(fused["cost"], plain["cost"], atol=1e-6)

    # Eq. 2 costs from the fused outputs = XLA (bf16 rollouts + td3_value) = NumPy eq. 2.
    got = mpc_lib._terminal(cfg, fused["cost"], fused["at_goal"], fused["value"])
    ref = sequence_costs(dataclasses.replace(cfg, backend="xla"), dcfg, st, obs, goal, acts, value_net_fn(net))
    np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-4)
    for b in range(2):
        v = np.asarray(td3_value(tcfg, ts, final_xla[b], jnp.broadcast_to(goal[b], (64, 2))))
        np.testing.assert_allclose(got[b], _np_cost(np.asarray(xy[b]), goal[b], v), rtol=1e-4, atol=1e-4)


def test_fused_value_bf16_and_output_normalisation():
    """bfloat16 value operands stay close to td3_value; the output-normalisation actor works in-kernel."""
    dcfg, st = _tiny_model(E=1, obs_dim=29, act_dim=8)
    tcfg, ts = _small_td3(output_normalisation=True)
    net = td3_value_net(tcfg, ts)
    cfg = MPCConfig(num_samples=64, horizon=2, block_rows=32, hidden_chunk=16, out_chunk=16, value_chunk=16)
    assert cfg.value_dtype == "bfloat16" and cfg.fuse_value
    obs = np.random.default_rng(2).normal(size=(1, 29)).astype(np.float32)
    goal = obs[:, :2] + np.array([[0.3, 0.2]], np.float32)
    acts = sample_action_sequences(jax.random.key(4), cfg, 1, 8)
    ref = sequence_costs(dataclasses.replace(cfg, backend="xla"), dcfg, st, obs, goal, acts, value_net_fn(net))
    got = sequence_costs(cfg, dcfg, st, obs, goal, acts, interpret=INTERPRET, value_net=net)
    assert float(jnp.std(ref)) > 0.1
    np.testing.assert_allclose(got, ref, atol=0.02 * float(jnp.max(jnp.abs(ref))))
    assert float(jnp.max(jnp.abs(got - ref))) > 0  # the bf16 kernel value was used, not the XLA one


def test_in_kernel_sampler():
    """The kernel's own draws equal _kernel_rng_actions (so the chosen first action is recovered
    exactly), and they look uniform on [-1, 1) with independent lanes, rows and steps."""
    dcfg, st = _tiny_model(E=1, obs_dim=29, act_dim=8)
    cfg = MPCConfig(num_samples=32, horizon=2, block_rows=16, hidden_chunk=16, out_chunk=16, use_value=False)
    obs = jnp.asarray(np.random.default_rng(3).normal(size=(2, 29)).astype(np.float32))
    goal = obs[:, :2] + 0.4
    seeds = mpc_lib._rng_seeds(jax.random.key(3), 2)
    fd = dynamics_fold(dcfg, st, jnp.bfloat16)
    acts = mpc_lib._kernel_rng_actions(seeds, 2, 32, 16, 8)
    drawn = mpc_lib._rollout_pallas(cfg, dcfg, fd, obs, goal, seeds, interpret=INTERPRET, want_final=False)
    given = mpc_lib._rollout_pallas(cfg, dcfg, fd, obs, goal, acts, interpret=INTERPRET, want_final=False)
    np.testing.assert_array_equal(drawn["cost"], given["cost"])
    # State and action as one interleaved first-layer operand: the same function.
    joined = mpc_lib._rollout_pallas(dataclasses.replace(cfg, join_input=True), dcfg, fd, obs, goal, seeds,
                                     interpret=INTERPRET, want_final=False)
    np.testing.assert_allclose(joined["cost"], given["cost"], atol=1e-5)
    rows = jnp.asarray([[5], [20]])
    np.testing.assert_array_equal(mpc_lib._kernel_rng_actions(seeds, 2, 32, 16, 8, t=0, rows=rows)[:, 0],
                                  acts[jnp.arange(2), 0, rows[:, 0], :8])
    assert not np.any(np.asarray(acts[..., 8:], np.float32))  # padding lanes are zero
    x = np.asarray(mpc_lib._kernel_rng_actions(mpc_lib._rng_seeds(jax.random.key(0), 4), 3, 4096, 16, 8),
                   np.float32)[..., :8]
    assert x.min() >= -1.0 and x.max() <= 1.0
    assert abs(x.mean()) < 0.01 and abs(x.var() - 1 / 3) < 0.01
    flat = x.reshape(-1, 8)
    assert np.abs(np.corrcoef(flat.T) - np.eye(8)).max() < 0.01  # lanes
    assert abs(np.corrcoef(x[:, :, :-1, 0].ravel(), x[:, :, 1:, 0].ravel())[0, 1]) < 0.01  # rows
    assert abs(np.corrcoef(x[:, 0].ravel(), x[:, 1].ravel())[0, 1]) < 0.01  # steps
    assert abs(np.corrcoef(x[0].ravel(), x[1].ravel())[0, 1]) < 0.01  # environments
