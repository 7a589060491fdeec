"""Learner benchmarks: MPC decisions/s, TD3 gradient steps/s, dynamics-model steps/s.

    python experiments/bench_learners.py                 # full sizes (GPU)
    python experiments/bench_learners.py --small         # CPU-sized smoke run
    python experiments/bench_learners.py --quality DATA  # + action-quality evidence (bf16, ensemble)

MPC: one decision = M x K rollout steps of the 2 x 500 dynamics MLP (about 55.5 GFLOP at M = 14,000,
K = 7 and the ant's 29-d state) plus the terminal value min(Q1, Q2)(s_K, g, pi(s_K, g)) of the TD3
critic on the M final states. Timings are medians over repeated calls of the jitted batched decision
(fresh key and inputs each call, results blocked on), after warm-up calls that compile.

Writes a JSON (device, versions, exact command, every number) and prints a table.
Helpers for the evidence in experiments/results/mpc_evidence.md:
  --make-ant-data PATH   random-action ant transitions from MuJoCo C (brax's ant model; CPU)
  --replay-quality NPZ   replay the sequences chosen on the GPU in MuJoCo C: true eq. 2 outcome
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)


def _versions():
    import jax
    out = {"python": platform.python_version(), "jax": jax.__version__}
    for mod in ("jaxlib", "flax", "optax", "numpy"):
        try:
            out[mod] = __import__(mod).__version__
        except Exception:  # pragma: no cover
            pass
    return out


def _device():
    import jax
    d = jax.devices()[0]
    return {"platform": d.platform, "kind": getattr(d, "device_kind", str(d)), "count": jax.device_count()}


def _time(fn, args_list, warmup=2, reps=5):
    """Median seconds per call; args rotate over args_list."""
    import jax
    for i in range(warmup):
        jax.block_until_ready(fn(*args_list[i % len(args_list)]))
    ts = []
    for i in range(reps):
        a = args_list[i % len(args_list)]
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*a))
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), ts


# ------------------------------------------------------------------------------------------------
# MPC
# ------------------------------------------------------------------------------------------------

def _value_fn(td3_cfg, td3_state):
    import jax.numpy as jnp
    from dscpp_jax.td3 import td3_value

    def vf(s, g):
        return td3_value(td3_cfg, td3_state, s, jnp.broadcast_to(g, s[:, :2].shape))

    return vf


def _mpc_variant(name):
    """name -> (MPCConfig, matmul precision or None).

    Suffixes: "_join" / "_split" state and action as one first-layer operand / as two (default:
    joined from 32 environments up); "_krng" / "_jrng" action sequences drawn inside the kernel / by jax.random; "_vbf16" value_fn matmuls in single bf16 passes (XLA value); "_xv" value through XLA
    after the kernel (value_fn, as before the fused value); "_fv32" fused value with float32 (TF32)
    operands; "_mean" ensemble mean. Pallas names: pallas_BM<rows>_W<warps>_S<stages>_C<hidden
    block>_N<out block>_VC<value block>; "pallas" alone is the library default tiling.
    """
    from dscpp_jax.mpc import MPCConfig
    if name.endswith("_join") or name.endswith("_split"):  # one first-layer operand or two
        join = name.endswith("_join")
        cfg, prec = _mpc_variant(name[:-len("_join" if join else "_split")])
        return dataclasses.replace(cfg, join_input=join), prec
    if name.endswith("_krng") or name.endswith("_jrng"):  # sequences drawn in the kernel / by jax.random
        cfg, prec = _mpc_variant(name[:-len("_krng")])
        return dataclasses.replace(cfg, kernel_rng=name.endswith("_krng")), prec
    if name.endswith("_xv"):
        cfg, prec = _mpc_variant(name[:-len("_xv")])
        return dataclasses.replace(cfg, fuse_value=False), prec
    if name.endswith("_fv32"):
        cfg, prec = _mpc_variant(name[:-len("_fv32")])
        return dataclasses.replace(cfg, value_dtype="float32"), prec
    if name.endswith("_vbf16"):
        cfg, prec = _mpc_variant(name[:-len("_vbf16")])
        return dataclasses.replace(cfg, value_precision="bfloat16"), prec
    if name.endswith("_mean"):
        cfg, prec = _mpc_variant(name[:-len("_mean")])
        return dataclasses.replace(cfg, ensemble_mode="mean"), prec
    base = dict(backend="xla", compute_dtype="float32")
    if name == "xla_f32":
        return MPCConfig(**base), None
    if name == "xla_f32_highest":
        return MPCConfig(**base), "highest"
    if name == "xla_bf16":
        return MPCConfig(backend="xla", compute_dtype="bfloat16"), None
    if name.startswith("pallas"):  # pallas_BM<rows>_W<warps>_S<stages>_C<chunk>
        kw = {}
        for p in name.split("_")[1:]:
            if p.startswith("VC"):
                kw["value_chunk"] = int(p[2:])
            elif p.startswith("BM"):
                kw["block_rows"] = int(p[2:])
            elif p.startswith("W"):
                kw["num_warps"] = int(p[1:])
            elif p.startswith("S"):
                kw["num_stages"] = int(p[1:])
            elif p.startswith("C"):
                kw["hidden_chunk"] = int(p[1:])
            elif p.startswith("N"):
                kw["out_chunk"] = int(p[1:])
        return MPCConfig(backend="pallas", compute_dtype="bfloat16", **kw), None
    raise ValueError(f"unknown MPC variant {name!r}")


def bench_mpc(variants, env_sizes, num_samples, horizon, use_values=(True,), obs_dim=29, act_dim=8,
              ensemble_size=1, reps=5, log=print, on_row=None):
    import jax
    import jax.numpy as jnp
    from dscpp_jax.dynamics import DynamicsConfig, dynamics_fit_normaliser, dynamics_init
    from dscpp_jax.mpc import mpc_actions, mpc_flops_per_decision, td3_value_net
    from dscpp_jax.td3 import TD3Config, td3_init

    key = jax.random.key(0)
    dcfg = DynamicsConfig(ensemble_size=ensemble_size)
    st = dynamics_init(key, obs_dim, act_dim, dcfg)
    rng = np.random.default_rng(0)
    o = rng.normal(size=(4096, obs_dim)).astype(np.float32)
    a = rng.uniform(-1, 1, size=(4096, act_dim)).astype(np.float32)
    st = dynamics_fit_normaliser(st, o, a, o + 0.05 * rng.normal(size=o.shape).astype(np.float32), None, dcfg)
    tcfg = TD3Config.model_based()
    tst = td3_init(jax.random.key(1), obs_dim, 2, act_dim, tcfg)
    vf = _value_fn(tcfg, tst)
    vnet = td3_value_net(tcfg, tst)
    rows = []
    for name in variants:
        for use_value in use_values:
            for B in env_sizes:
                cfg, prec = _mpc_variant(name)
                cfg = dataclasses.replace(cfg, num_samples=num_samples, horizon=horizon, use_value=use_value)
                flops = mpc_flops_per_decision(cfg, obs_dim, act_dim, dcfg.hidden)
                if cfg.ensemble_mode == "mean":  # every member rolls out every sequence
                    flops *= ensemble_size

                def decide(s, k, obs, goal, cfg=cfg):
                    if not cfg.use_value:
                        return mpc_actions(cfg, dcfg, s, k, obs, goal)
                    return mpc_actions(cfg, dcfg, s, k, obs, goal, vf, value_net=vnet)

                f = jax.jit(decide)
                args = []
                for i in range(3):
                    obs = jnp.asarray(rng.normal(size=(B, obs_dim)).astype(np.float32))
                    goal = obs[:, :2] + jnp.asarray(rng.normal(size=(B, 2)).astype(np.float32))
                    args.append((st, jax.random.key(10 + i), obs, goal))
                row = {"variant": name, "envs": B, "use_value": use_value, "num_samples": num_samples,
                       "horizon": horizon, "ensemble_size": ensemble_size, "precision": prec or "default",
                       "value_path": (("fused_" + cfg.value_dtype if cfg.fuse_value else "xla")
                                      if use_value and cfg.backend == "pallas" else
                                      ("xla" if use_value else "none"))}
                try:
                    t0 = time.perf_counter()
                    ctx = jax.default_matmul_precision(prec) if prec else _null()
                    with ctx:
                        jax.block_until_ready(f(*args[0]))
                        row["compile_s"] = time.perf_counter() - t0
                        sec, ts = _time(f, args, warmup=1, reps=reps)
                    row.update(seconds_per_call=sec, decisions_per_s=B / sec,
                               tflops=flops * B / sec / 1e12, times=ts)
                except Exception as e:  # noqa: BLE001 - report and go on
                    row["error"] = f"{type(e).__name__}: {str(e)[:400]}"
                rows.append(row)
                log(_fmt_mpc(row))
                if on_row is not None:
                    on_row(row)
    return rows


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False


def _run_cost_jobs(jobs, log):
    """{name: (thunk, matmul precision or None)} -> {name: costs as NumPy}; a variant that fails
    (e.g. a kernel that does not compile on this device) is logged and left out."""
    import jax
    costs = {}
    for name, (thunk, prec) in jobs.items():
        try:
            with (jax.default_matmul_precision(prec) if prec else _null()):
                costs[name] = np.asarray(thunk())
        except Exception as e:  # noqa: BLE001
            log(f"  {name}: ERROR {type(e).__name__}: {str(e)[:300]}")
    return costs


def _fmt_mpc(r):
    if "error" in r:
        return f"  {r['variant']:<28} envs={r['envs']:<4} value={int(r['use_value'])}  ERROR {r['error'][:160]}"
    return (f"  {r['variant']:<28} envs={r['envs']:<4} value={int(r['use_value'])}  "
            f"{r['decisions_per_s']:>9.1f} dec/s  {r['tflops']:>7.1f} TFLOP/s  "
            f"({1e3 * r['seconds_per_call']:.2f} ms/call, compile {r.get('compile_s', 0):.1f} s)")


# ------------------------------------------------------------------------------------------------
# TD3 and dynamics steps/s
# ------------------------------------------------------------------------------------------------

def bench_td3(batch_sizes, num_steps, obs_dim=29, act_dim=8, log=print):
    import jax
    import jax.numpy as jnp
    from dscpp_jax.replay import Transition
    from dscpp_jax.td3 import TD3Config, td3_init, td3_update

    rows = []
    for preset in ("model_based", "model_free"):
        for bs in batch_sizes:
            cfg = getattr(TD3Config, preset)(batch_size=bs)
            st = td3_init(jax.random.key(0), obs_dim, 2, act_dim, cfg)
            k = jax.random.split(jax.random.key(1), 6)
            batches = Transition(
                obs=jax.random.normal(k[0], (num_steps, bs, obs_dim)),
                action=jax.random.uniform(k[1], (num_steps, bs, act_dim), minval=-1, maxval=1),
                reward=-(jax.random.uniform(k[2], (num_steps, bs)) < 0.9).astype(jnp.float32),
                next_obs=jax.random.normal(k[3], (num_steps, bs, obs_dim)),
                goal=jax.random.normal(k[4], (num_steps, bs, 2)),
                discount=jnp.ones((num_steps, bs)),
            )

            def run(state, batches, key, cfg=cfg):
                def body(s, xs):
                    b, kk = xs
                    s, m = td3_update(cfg, s, b, kk)
                    return s, m["critic_loss"]
                return jax.lax.scan(body, state, (batches, jax.random.split(key, num_steps)))

            f = jax.jit(run)
            sec, _ = _time(f, [(st, batches, jax.random.key(i)) for i in range(2)], warmup=1, reps=3)
            row = {"preset": preset, "batch_size": bs, "steps_per_call": num_steps,
                   "grad_steps_per_s": num_steps / sec}
            rows.append(row)
            log(f"  td3 {preset:<12} batch={bs:<5} {row['grad_steps_per_s']:>10.0f} gradient steps/s")
    return rows


def bench_dynamics(ensemble_sizes, batch_size, num_steps, buffer_size, obs_dim=29, act_dim=8, log=print):
    import jax
    from dscpp_jax.dynamics import DynamicsConfig, dynamics_fit_normaliser, dynamics_init, dynamics_train

    rows = []
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(buffer_size, obs_dim)).astype(np.float32)
    act = rng.uniform(-1, 1, size=(buffer_size, act_dim)).astype(np.float32)
    nxt = obs + 0.05 * rng.normal(size=obs.shape).astype(np.float32)
    mask = np.ones(buffer_size, bool)
    buf = tuple(jax.device_put(x) for x in (obs, act, nxt, mask))
    for E in ensemble_sizes:
        cfg = DynamicsConfig(ensemble_size=E, batch_size=batch_size)
        st = dynamics_fit_normaliser(dynamics_init(jax.random.key(0), obs_dim, act_dim, cfg), *buf, cfg=cfg)
        f = jax.jit(lambda s, b, k, cfg=cfg: dynamics_train(cfg, s, b, k, num_steps))
        sec, _ = _time(f, [(st, buf, jax.random.key(i)) for i in range(2)], warmup=1, reps=3)
        row = {"ensemble_size": E, "batch_size": batch_size, "buffer": buffer_size,
               "steps_per_call": num_steps, "steps_per_s": num_steps / sec,
               "member_steps_per_s": E * num_steps / sec}
        rows.append(row)
        log(f"  dynamics E={E:<3} batch={batch_size:<5} {row['steps_per_s']:>10.0f} steps/s "
            f"({row['member_steps_per_s']:.0f} member-steps/s)")
    return rows


# ------------------------------------------------------------------------------------------------
# Action quality: bf16 vs float32, ensemble mean vs one member per sequence
# ------------------------------------------------------------------------------------------------

def make_ant_data(path, n_steps=30000, episode=200, seed=0, frame_skip=5):
    """Random-action transitions of brax's ant model in MuJoCo C (obs = qpos[:15] + qvel[:14])."""
    import mujoco
    import brax

    xml = os.path.join(os.path.dirname(brax.__file__), "envs", "assets", "ant.xml")
    model = mujoco.MjModel.from_xml_path(xml)
    data = mujoco.MjData(model)
    rng = np.random.default_rng(seed)
    obs, act, nxt = [], [], []
    for t in range(n_steps):
        if t % episode == 0:
            mujoco.mj_resetData(model, data)
            data.qpos[:] += rng.uniform(-0.1, 0.1, model.nq)
            data.qvel[:] += 0.1 * rng.normal(size=model.nv)
            mujoco.mj_forward(model, data)
        o = np.concatenate([data.qpos[:15], data.qvel[:14]]).astype(np.float32)
        a = rng.uniform(-1, 1, model.nu).astype(np.float32)
        data.ctrl[:] = a
        for _ in range(frame_skip):
            mujoco.mj_step(model, data)
        obs.append(o), act.append(a), nxt.append(np.concatenate([data.qpos[:15], data.qvel[:14]]).astype(np.float32))
    np.savez_compressed(path, obs=np.stack(obs), act=np.stack(act), next_obs=np.stack(nxt),
                        frame_skip=frame_skip, xml=xml)
    print(f"wrote {path}: {len(obs)} transitions, dt per step {model.opt.timestep * frame_skip:.3f} s")


QUALITY_V_SCALE = 0.1  # synthetic terminal value: V = -max(||xy - g|| - tol, 0) / QUALITY_V_SCALE


def _synthetic_value(s, g):
    import jax.numpy as jnp
    return -jnp.maximum(jnp.linalg.norm(s[:, :2] - g, axis=-1) - 0.6, 0.0) / QUALITY_V_SCALE


def quality(data_path, out_npz, num_samples, horizon, n_starts, train_steps, ensemble=5, log=print,
            pallas_variant="pallas"):
    """Same candidate sequences scored by every variant; chosen sequences saved for a true replay."""
    import jax
    import jax.numpy as jnp
    from dscpp_jax.dynamics import (DynamicsConfig, dynamics_fit_normaliser, dynamics_init, dynamics_metrics,
                                    dynamics_train)
    from dscpp_jax.mpc import MPCConfig, sequence_costs, sample_action_sequences

    d = np.load(data_path)
    obs, act, nxt = d["obs"], d["act"], d["next_obs"]
    n = obs.shape[0]
    ntr = int(0.9 * n)
    tr = (obs[:ntr], act[:ntr], nxt[:ntr])
    te = (obs[ntr:], act[ntr:], nxt[ntr:])
    models = {}
    for E in (1, ensemble):
        cfg = DynamicsConfig(ensemble_size=E)
        st = dynamics_fit_normaliser(dynamics_init(jax.random.key(E), 29, 8, cfg), *tr, None, cfg)
        t0 = time.perf_counter()
        st, m = jax.jit(lambda s, b, k, cfg=cfg: dynamics_train(cfg, s, b, k, train_steps))(st, tr, jax.random.key(0))
        jax.block_until_ready(st)
        met = {k: float(v) for k, v in dynamics_metrics(cfg, st, *te).items()}
        log(f"  trained E={E}: {train_steps} steps in {time.perf_counter() - t0:.1f} s, held-out {met}")
        models[E] = (cfg, st, met)

    rng = np.random.default_rng(1)
    starts = rng.choice(te[0].shape[0], n_starts, replace=False)
    s0 = te[0][starts]
    ang = rng.uniform(0, 2 * np.pi, n_starts)
    goal = s0[:, :2] + np.stack([np.cos(ang), np.sin(ang)], -1) * rng.uniform(0.8, 1.6, (n_starts, 1))
    goal = goal.astype(np.float32)
    base = MPCConfig(num_samples=num_samples, horizon=horizon, use_value=True)
    pcfg, _ = _mpc_variant(pallas_variant)
    pk = {f.name: getattr(pcfg, f.name) for f in dataclasses.fields(pcfg)
          if f.name in ("backend", "compute_dtype", "block_rows", "num_warps", "num_stages", "hidden_chunk", "out_chunk")}
    log(f"  fused-kernel settings in this study: {pk}")
    acts = sample_action_sequences(jax.random.key(123), base, n_starts, 8)
    variants = {
        "E1_f32_highest": (1, dict(backend="xla", compute_dtype="float32"), "highest"),
        "E1_f32_default": (1, dict(backend="xla", compute_dtype="float32"), None),
        "E1_xla_bf16": (1, dict(backend="xla", compute_dtype="bfloat16"), None),
        "E1_pallas_bf16": (1, dict(pk), None),
        f"E{ensemble}_mean_f32": (ensemble, dict(backend="xla", compute_dtype="float32", ensemble_mode="mean"), "highest"),
        f"E{ensemble}_member_f32": (ensemble, dict(backend="xla", compute_dtype="float32", ensemble_mode="member"), "highest"),
        f"E{ensemble}_member_pallas_bf16": (ensemble, dict(pk, ensemble_mode="member"), None),
        f"E{ensemble}_mean_pallas_bf16": (ensemble, dict(pk, ensemble_mode="mean"), None),
    }
    jobs = {}
    for name, (E, kw, prec) in variants.items():
        cfg = dataclasses.replace(base, **kw)
        dcfg, st, _ = models[E]
        f = jax.jit(lambda s, a, cfg=cfg, dcfg=dcfg: sequence_costs(cfg, dcfg, s, jnp.asarray(s0), jnp.asarray(goal), a,
                                                                    _synthetic_value))
        jobs[name] = (lambda f=f, st=st: f(st, acts), prec)
    costs = _run_cost_jobs(jobs, log)
    acts_np = np.asarray(acts)
    summary = {}
    ref = costs.get("E1_f32_highest")
    for name, c in costs.items():
        idx = c.argmin(1)
        s = {"chosen_pred_cost_mean": float(c[np.arange(n_starts), idx].mean())}
        if ref is not None and name.startswith("E1"):
            ridx = ref.argmin(1)
            regret = ref[np.arange(n_starts), idx] - ref[np.arange(n_starts), ridx]
            spread = np.median(ref, 1) - ref[np.arange(n_starts), ridx]
            rank = (ref < ref[np.arange(n_starts), idx][:, None]).sum(1)
            s.update(argmin_agreement=float((idx == ridx).mean()), regret_mean=float(regret.mean()),
                     regret_over_median_gap=float((regret / np.maximum(spread, 1e-9)).mean()),
                     rank_under_f32_mean=float(rank.mean()), rank_under_f32_max=int(rank.max()),
                     first_action_l2_to_f32_choice=float(np.linalg.norm(
                         acts_np[np.arange(n_starts), idx, 0] - acts_np[np.arange(n_starts), ridx, 0], axis=-1).mean()),
                     max_abs_cost_diff=float(np.abs(c - ref).max()))
        summary[name] = s
        log(f"  quality {name:<28} {s}")
    chosen = {name: acts_np[np.arange(n_starts), c.argmin(1)] for name, c in costs.items()}
    np.savez_compressed(out_npz, s0=s0, goal=goal, random_seq=acts_np[:, 0], **{f"seq_{k}": v for k, v in chosen.items()})
    return {"models": {str(E): m[2] for E, m in models.items()}, "variants": summary,
            "num_samples": num_samples, "horizon": horizon, "n_starts": n_starts, "train_steps": train_steps,
            "v_scale": QUALITY_V_SCALE}


def _fit_td3_value(obs_train, obs_test, steps, batch=1024, goal_radius=3.0, seed=0, log=print):
    """A TD3 actor + twin critic (model-based preset, 2 x 256) whose min(Q1, Q2)(s, g, pi(s, g)) is
    regressed onto the synthetic distance value, so the terminal value is a real critic network with
    a known meaning. Returns (TD3Config, TD3State, held-out RMSE of V)."""
    import jax
    import jax.numpy as jnp
    import optax
    from dscpp_jax.networks import TwinCritic
    from dscpp_jax.td3 import TD3Config, td3_init, td3_value

    tcfg = TD3Config.model_based()
    st = td3_init(jax.random.key(seed), obs_train.shape[1], 2, 8, tcfg)
    critic = TwinCritic(hidden=tcfg.hidden)
    tx = optax.adam(1e-3)
    xs = jnp.asarray(obs_train)

    def sample(key, n, pool):
        k1, k2, k3, k4 = jax.random.split(key, 4)
        s = pool[jax.random.randint(k1, (n,), 0, pool.shape[0])]
        ang = jax.random.uniform(k2, (n,), maxval=2 * np.pi)
        r = goal_radius * jnp.sqrt(jax.random.uniform(k3, (n,)))
        g = s[:, :2] + r[:, None] * jnp.stack([jnp.cos(ang), jnp.sin(ang)], -1)
        a = jax.random.uniform(k4, (n, 8), minval=-1, maxval=1)
        return s, g, a, _synthetic_value(s, g)

    def loss_fn(params, s, g, a, y):
        return jnp.mean(jnp.square(critic.apply(params, s, g, a) - y[None]))

    @jax.jit
    def train(params, key):
        def body(carry, k):
            params, opt = carry
            s, g, a, y = sample(k, batch, xs)
            l, grad = jax.value_and_grad(loss_fn)(params, s, g, a, y)
            upd, opt = tx.update(grad, opt, params)
            return (optax.apply_updates(params, upd), opt), l
        (params, _), ls = jax.lax.scan(body, (params, tx.init(params)), jax.random.split(key, steps))
        return params, ls

    t0 = time.perf_counter()
    params, ls = train(st.critic_params, jax.random.key(seed + 1))
    st = st.replace(critic_params=params, target_critic_params=params)
    s, g, _, y = sample(jax.random.key(seed + 2), 8192, jnp.asarray(obs_test))
    v = td3_value(tcfg, st, s, g)
    rmse = float(jnp.sqrt(jnp.mean(jnp.square(v - y))))
    log(f"  fitted TD3 critic to the synthetic value: {steps} steps in {time.perf_counter() - t0:.1f} s, "
        f"final loss {float(ls[-1]):.3f}, held-out V RMSE {rmse:.3f} (V std {float(jnp.std(y)):.2f})")
    return tcfg, st, rmse


def value_quality(data_path, out_npz, num_samples, horizon, n_starts, train_steps, critic_steps,
                  pallas_variant="pallas", log=print):
    """Terminal value in the fused kernel vs through XLA, with a real TD3 critic network.

    One E = 1 dynamics model (as in `quality`), a TD3 actor + twin critic fitted to the synthetic
    distance value, and the same candidate sequences scored by: XLA float32 (highest precision,
    rollouts and value: the reference), the fused kernel with the value through XLA after the kernel
    (default precision; the path before the value was fused), and the value fused into the kernel
    with bfloat16 or float32 (TF32) operands. Chosen sequences are saved for the MuJoCo replay.
    """
    import jax
    import jax.numpy as jnp
    from dscpp_jax.dynamics import DynamicsConfig, dynamics_fit_normaliser, dynamics_init, dynamics_train
    from dscpp_jax.mpc import MPCConfig, sequence_costs, sample_action_sequences, td3_value_net, value_net_fn

    d = np.load(data_path)
    obs, act, nxt = d["obs"], d["act"], d["next_obs"]
    ntr = int(0.9 * obs.shape[0])
    tr = (obs[:ntr], act[:ntr], nxt[:ntr])
    dcfg = DynamicsConfig(ensemble_size=1)
    st = dynamics_fit_normaliser(dynamics_init(jax.random.key(1), 29, 8, dcfg), *tr, None, dcfg)
    st, _ = jax.jit(lambda s, b, k: dynamics_train(dcfg, s, b, k, train_steps))(st, tr, jax.random.key(0))
    tcfg, tst, rmse = _fit_td3_value(obs[:ntr], obs[ntr:], critic_steps, log=log)
    net = td3_value_net(tcfg, tst)
    vf = value_net_fn(net)

    rng = np.random.default_rng(1)  # the same starts and goals as `quality`
    te0 = obs[ntr:]
    starts = rng.choice(te0.shape[0], n_starts, replace=False)
    s0 = te0[starts]
    ang = rng.uniform(0, 2 * np.pi, n_starts)
    goal = (s0[:, :2] + np.stack([np.cos(ang), np.sin(ang)], -1) * rng.uniform(0.8, 1.6, (n_starts, 1))).astype(np.float32)
    base = MPCConfig(num_samples=num_samples, horizon=horizon, use_value=True)
    pcfg, _ = _mpc_variant(pallas_variant)
    pk = {f.name: getattr(pcfg, f.name) for f in dataclasses.fields(pcfg)
          if f.name in ("backend", "compute_dtype", "block_rows", "num_warps", "num_stages", "hidden_chunk",
                        "out_chunk", "value_chunk", "join_input")}
    acts = sample_action_sequences(jax.random.key(123), base, n_starts, 8)
    variants = {
        "tdv_f32_highest": (dict(backend="xla", compute_dtype="float32"), "highest", vf, None),
        "tdv_pallas_xla_value": (dict(pk, fuse_value=False), None, vf, None),
        "tdv_pallas_fused_bf16": (dict(pk, value_dtype="bfloat16"), None, None, net),
        "tdv_pallas_fused_f32": (dict(pk, value_dtype="float32"), None, None, net),
    }
    jobs = {}
    for name, (kw, prec, fn, vn) in variants.items():
        cfg = dataclasses.replace(base, **kw)
        f = jax.jit(lambda s, a, cfg=cfg, fn=fn, vn=vn: sequence_costs(cfg, dcfg, s, jnp.asarray(s0), jnp.asarray(goal),
                                                                      a, fn, value_net=vn))
        jobs[name] = (lambda f=f: f(st, acts), prec)
    costs = _run_cost_jobs(jobs, log)
    acts_np = np.asarray(acts)
    summary = {}
    ar = np.arange(n_starts)
    for ref_name in ("tdv_f32_highest", "tdv_pallas_xla_value"):
        ref = costs.get(ref_name)
        if ref is None:
            continue
        ridx = ref.argmin(1)
        spread = np.median(ref, 1) - ref[ar, ridx]
        for name, c in costs.items():
            idx = c.argmin(1)
            regret = ref[ar, idx] - ref[ar, ridx]
            rank = (ref < ref[ar, idx][:, None]).sum(1)
            summary.setdefault(name, {"chosen_pred_cost_mean": float(c[ar, idx].mean())})[f"vs_{ref_name}"] = dict(
                argmin_agreement=float((idx == ridx).mean()), regret_mean=float(regret.mean()),
                regret_over_median_gap=float((regret / np.maximum(spread, 1e-9)).mean()),
                rank_mean=float(rank.mean()), rank_max=int(rank.max()),
                max_abs_cost_diff=float(np.abs(c - ref).max()),
                mean_abs_cost_diff=float(np.abs(c - ref).mean()))
    for name, sm in summary.items():
        log(f"  value quality {name:<24} {sm}")
    np.savez_compressed(out_npz, s0=s0, goal=goal, random_seq=acts_np[:, 0],
                        **{f"seq_{k}": acts_np[ar, c.argmin(1)] for k, c in costs.items()})
    return {"variants": summary, "critic_value_rmse": rmse, "critic_steps": critic_steps, "num_samples": num_samples,
            "horizon": horizon, "n_starts": n_starts, "train_steps": train_steps, "kernel": pk,
            "v_scale": QUALITY_V_SCALE}


def replay_quality(npz_path, data_path, gamma=0.95, tol=0.6, ref=None):
    """True eq. 2 cost (same synthetic V at the true final state) of each variant's chosen sequences."""
    import mujoco
    q = np.load(npz_path)
    d = np.load(data_path)
    model = mujoco.MjModel.from_xml_path(str(d["xml"]))
    data = mujoco.MjData(model)
    fs = int(d["frame_skip"])
    s0, goal = q["s0"], q["goal"]
    res = {}
    per_start = {}
    names = ["random_seq"] + [k for k in q.files if k.startswith("seq_")]
    for name in names:
        seqs = q[name]
        costs, dists = [], []
        for i in range(s0.shape[0]):
            mujoco.mj_resetData(model, data)
            data.qpos[:15] = s0[i, :15]
            data.qvel[:14] = s0[i, 15:29]
            mujoco.mj_forward(model, data)
            c = 0.0
            for j in range(seqs.shape[1]):
                data.ctrl[:] = seqs[i, j]
                for _ in range(fs):
                    mujoco.mj_step(model, data)
                dj = np.linalg.norm(data.qpos[:2] - goal[i])
                c += gamma ** j * (dj > tol)
            v = -max(dj - tol, 0.0) / QUALITY_V_SCALE
            c -= gamma ** seqs.shape[1] * v
            costs.append(c), dists.append(dj)
        key = name.replace("seq_", "")
        per_start[key] = (np.asarray(costs), np.asarray(dists))
    if ref is None:
        ref = next((r for r in ("E1_f32_highest", "tdv_f32_highest") if r in per_start), "random_seq")
    rc, rd = per_start[ref]
    n = len(rc)
    for key, (costs, dists) in per_start.items():
        dc, dd = costs - rc, dists - rd
        res[key] = {"true_cost_mean": float(costs.mean()), "true_cost_sem": float(costs.std() / np.sqrt(n)),
                    "true_final_dist_mean": float(dists.mean()),
                    f"paired_cost_diff_vs_{ref}": float(dc.mean()),
                    f"paired_cost_diff_sem": float(dc.std(ddof=1) / np.sqrt(n)) if n > 1 else 0.0,
                    f"paired_dist_diff_vs_{ref}": float(dd.mean()),
                    "paired_dist_diff_sem": float(dd.std(ddof=1) / np.sqrt(n)) if n > 1 else 0.0}
        print(f"  {key:<30} true cost {costs.mean():8.3f}  paired diff vs {ref} {dc.mean():+.3f} ± "
              f"{res[key]['paired_cost_diff_sem']:.3f}   final distance {dists.mean():.3f} "
              f"(paired {dd.mean():+.4f} ± {res[key]['paired_dist_diff_sem']:.4f})")
    return res


# ------------------------------------------------------------------------------------------------

def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--small", action="store_true", help="CPU-sized run (M=1000, envs 1 and 4, few steps); "
                   "the default when no GPU is present, unless --full")
    p.add_argument("--full", action="store_true", help="full sizes even without a GPU")
    p.add_argument("--out", default=None, help="JSON path (default experiments/results/bench_learners[_small].json)")
    p.add_argument("--variants", default=None, help="comma-separated MPC variants (xla_f32, xla_f32_highest, "
                   "xla_bf16, pallas_BM64_W4_S1_C128, ...)")
    p.add_argument("--envs", default=None, help="comma-separated env counts (default 1,32,128,256)")
    p.add_argument("--tune", default=None, help="comma-separated pallas variants to try at --tune-envs first; "
                   "the fastest joins --variants")
    p.add_argument("--tune-envs", type=int, default=128)
    p.add_argument("--tune-value", action="store_true", help="tune with the terminal value (fused) instead of without")
    p.add_argument("--tune-more", default=None, help="comma-separated name parts appended to the fastest tuned "
                   "kernel and timed in a second round (e.g. VC32,VC128); the fastest of both rounds wins")
    p.add_argument("--tune-extra", default="_xv,_fv32", help="suffixes of the tuned kernel also timed in the main "
                   "table (default: value through XLA, fused value in float32)")
    p.add_argument("--no-value-envs", default=None, help="env counts also measured without the value term")
    p.add_argument("--ensemble", type=int, default=1)
    p.add_argument("--ensemble-extra", default=None, metavar="E:ENVS",
                   help="also time the best kernel with E members (member and mean modes) at ENVS envs")
    p.add_argument("--skip", default="", help="comma-separated sections to skip: mpc,td3,dynamics")
    p.add_argument("--quality", default=None, help="ant transitions .npz (--make-ant-data) for the quality study")
    p.add_argument("--quality-out", default=None, help="npz of chosen sequences (default next to --out)")
    p.add_argument("--quality-starts", type=int, default=512)
    p.add_argument("--quality-train-steps", type=int, default=3000)
    p.add_argument("--value-quality", action="store_true", help="with --quality DATA: fused vs XLA terminal "
                   "value with a TD3 critic fitted to the synthetic value (chosen sequences saved for the replay)")
    p.add_argument("--critic-steps", type=int, default=4000)
    p.add_argument("--skip-quality-study", action="store_true", help="with --value-quality: skip the "
                   "bf16/ensemble study")
    p.add_argument("--make-ant-data", default=None, metavar="PATH")
    p.add_argument("--replay-quality", default=None, metavar="NPZ", help="with --quality DATA: true replay")
    p.add_argument("--replay-ref", default=None, help="variant the replay's paired differences refer to "
                   "(default: the highest-precision float32 one)")
    args = p.parse_args(argv)

    if args.make_ant_data:
        make_ant_data(args.make_ant_data)
        return
    if args.replay_quality:
        res = replay_quality(args.replay_quality, args.quality, ref=args.replay_ref)
        out = args.out or os.path.join(ROOT, "experiments", "results", "bench_learners_quality_replay.json")
        with open(out, "w") as f:
            json.dump({"command": " ".join([os.path.basename(sys.executable)] + sys.argv), "replay": res}, f, indent=1)
        print(f"wrote {out}")
        return

    import jax
    small = args.small or (jax.default_backend() == "cpu" and not args.full)
    if small and not args.small:
        print("no GPU found: running the small CPU-sized benchmark (--full to force full sizes)")
    M = 1000 if small else 14000
    K = 7
    env_sizes = [int(x) for x in (args.envs or ("1,4" if small else "1,32,128,256")).split(",")]
    variants = (args.variants or ("xla_f32,xla_bf16" if small else "xla_f32,xla_bf16,pallas")).split(",")
    skip = set(filter(None, args.skip.split(",")))
    out = args.out or os.path.join(ROOT, "experiments", "results",
                                   "bench_learners_small.json" if small else "bench_learners.json")
    os.makedirs(os.path.dirname(out), exist_ok=True)
    res = {"command": " ".join(["python"] + [os.path.relpath(sys.argv[0], ROOT) if i == 0 else a
                                             for i, a in enumerate(sys.argv)]),
           "device": _device(), "versions": _versions(),
           "xla_flags": os.environ.get("XLA_FLAGS", ""), "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
           "mpc_setup": {"num_samples": M, "horizon": K, "obs_dim": 29, "action_dim": 8, "hidden": [500, 500],
                         "value": "td3_value (TD3Config.model_based, 2x256 twin critic + actor) on the M final states",
                         "gflop_per_decision_dynamics": None}}
    from dscpp_jax.mpc import MPCConfig, mpc_flops_per_decision
    res["mpc_setup"]["gflop_per_decision_dynamics"] = mpc_flops_per_decision(
        MPCConfig(num_samples=M, horizon=K), 29, 8) / 1e9
    print(f"device {res['device']}  versions {res['versions']}")

    def save():
        with open(out, "w") as f:
            json.dump(res, f, indent=1)

    if "td3" not in skip:
        print("TD3 gradient steps/s:")
        res["td3"] = bench_td3([100, 256], 50 if small else 2000)
        save()
    if "dynamics" not in skip:
        print("Dynamics-model steps/s:")
        res["dynamics"] = bench_dynamics([1] if small else [1, 5], 256 if small else 1024, 10 if small else 500,
                                         5000 if small else 300_000)
        save()
    res["mpc"] = []

    def add_row(row, key="mpc"):
        if row not in res.setdefault(key, []):
            res[key].append(row)
        save()

    if "mpc" not in skip and args.tune:
        print(f"MPC kernel tuning at {args.tune_envs} envs (M={M}, K={K}, "
              f"{'with the fused value' if args.tune_value else 'no value'}):")
        tune_rows = bench_mpc(args.tune.split(","), [args.tune_envs], M, K, use_values=(bool(args.tune_value),),
                              ensemble_size=args.ensemble, reps=3, on_row=lambda r: add_row(r, "mpc_tuning"))
        ok = [r for r in tune_rows if "error" not in r]
        if ok and args.tune_more:
            first = max(ok, key=lambda r: r["decisions_per_s"])["variant"]
            ok += [r for r in bench_mpc([f"{first}_{x}" for x in args.tune_more.split(",")], [args.tune_envs], M, K,
                                        use_values=(bool(args.tune_value),), ensemble_size=args.ensemble, reps=3,
                                        on_row=lambda r: add_row(r, "mpc_tuning")) if "error" not in r]
        if ok:
            best = max(ok, key=lambda r: r["decisions_per_s"])["variant"]
            res["mpc_best_kernel"] = best
            for v in [best] + [best + x for x in args.tune_extra.split(",") if x]:
                if v not in variants:
                    variants.append(v)
        save()
    if args.quality and not args.skip_quality_study:
        print("MPC action quality (same candidate sequences, synthetic distance value):")
        qout = args.quality_out or os.path.splitext(out)[0] + "_quality.npz"
        res["quality"] = quality(args.quality, qout, M, K, args.quality_starts,
                                 200 if small else args.quality_train_steps,
                                 pallas_variant=res.get("mpc_best_kernel", "pallas"))
        save()
    if "mpc" not in skip:
        print(f"MPC decisions/s (M={M}, K={K}, E={args.ensemble}):")
        bench_mpc(variants, env_sizes, M, K, use_values=(True,), ensemble_size=args.ensemble, on_row=add_row)
        if args.no_value_envs:
            nv = [int(x) for x in args.no_value_envs.split(",")]
            print("MPC without the value term (flat finite horizon):")
            value_only = ("_xv", "_fv32", "_vbf16")  # suffixes that change only the value term
            bench_mpc([v for v in variants if not v.endswith(value_only)], nv, M, K, use_values=(False,),
                      ensemble_size=args.ensemble, on_row=add_row)
        if args.ensemble_extra and "mpc_best_kernel" in res:
            E2, envs2 = (int(x) for x in args.ensemble_extra.split(":"))
            best = res["mpc_best_kernel"]
            print(f"MPC with an ensemble of {E2} (fused kernel, one member per sequence vs mean of members):")
            bench_mpc([best, best + "_mean"], [envs2], M, K, use_values=(True,), ensemble_size=E2, on_row=add_row)

    if args.quality and args.value_quality:
        print("MPC terminal value fused vs XLA (same candidate sequences, TD3 critic fitted to the synthetic value):")
        qout = os.path.splitext(out)[0] + "_value_quality.npz"
        res["value_quality"] = value_quality(args.quality, qout, M, K, args.quality_starts,
                                             200 if small else args.quality_train_steps,
                                             100 if small else args.critic_steps,
                                             pallas_variant=res.get("mpc_best_kernel", "pallas"))
        save()
    print(f"\nwrote {out}")
    print("\n| section | variant | envs | value | rate | TFLOP/s |\n|---|---|---|---|---|---|")
    for r in res.get("mpc", []):
        if "error" in r:
            print(f"| mpc | {r['variant']} | {r['envs']} | {int(r['use_value'])} | error | |")
        else:
            print(f"| mpc | {r['variant']} | {r['envs']} | {int(r['use_value'])} | "
                  f"{r['decisions_per_s']:.0f} dec/s | {r['tflops']:.1f} |")
    for r in res.get("td3", []):
        print(f"| td3 | {r['preset']} | batch {r['batch_size']} | | {r['grad_steps_per_s']:.0f} steps/s | |")
    for r in res.get("dynamics", []):
        print(f"| dynamics | E={r['ensemble_size']} | batch {r['batch_size']} | | {r['steps_per_s']:.0f} steps/s | |")


if __name__ == "__main__":
    main()
