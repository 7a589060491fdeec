"""Where the time of one `train_step` goes, per component, at several environment counts.

    python experiments/profile_train_step.py --env u_maze --num-envs 128 512 --out prof.json
    python experiments/profile_train_step.py --env point_u_maze --num-envs 16 --small   # CPU smoke

For each B it times (median of repeated jitted calls, results blocked on):
  env       T steps of the B vmapped environments with random actions (physics alone)
  mpc       one batched MPC decision for B environments (T of them per iteration)
  rollout_warmup / rollout_policy   the whole T-step collection scan (warm-up: random actions;
            policy: options, subgoals, MPC or actor, recording, replay writes)
  learn     TD3 + dynamics updates, classifier refits, chain growth (fresh chain: refits are cheap
            here; experiments/bench_options.py times refits on full buffers)
  td3       the iteration's TD3+HER gradient steps alone (part of learn); with --td3-blocks, also
            for each listed td3_sample_block (minibatches drawn per replay sampling call)
  train_step  the jitted train_step after warm-up
  learn_after_rollout  learn on the state a rollout leaves (its option executions mark rows
            for refitting), as in training
With --learn-parts, also each part of `learn` alone, on that state: the dynamics model's
normaliser fit and its gradient steps, the classifier refits, the chain's growth and metrics,
and the finiteness checks.
With --trained N, every time is taken on the state after N real training iterations (filled
buffers, a grown chain) instead of a fresh one. With --chained N, also N iterations one after
another, each on the state the last returned and with its metrics fetched, as `train`'s loop
runs them. Also recorded: `train_step`'s trace + lower and its XLA compile (a cache load where
JAX's persistent cache, on as in `train`, holds it). The XLA flags are `train`'s (fusion autotuner off, and
deterministic kernels where `train` turns them on) unless --xla-flags default.
Prints env steps/s for each. Writes JSON with the device, versions and command.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from dscpp_jax.td3 import TD3Config

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)


def _time(fn, *args, reps=3):
    import jax
    jax.block_until_ready(fn(*args))  # compile + warm
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def learn_parts(cfg, state, key, reps: int) -> dict:
    """Seconds of each part of `trainer.learn` alone, on `state` (see the module docstring)."""
    import jax
    import jax.numpy as jnp

    from dscpp_jax import acting, learning
    from dscpp_jax import trainer as T
    out = {}
    if cfg.model_based:
        out["dyn_normaliser_s"] = _time(jax.jit(lambda d, r: learning.fit_normaliser(cfg, d, r)),
                                        state.dyn, state.model_replay, reps=reps)
        out["dyn_updates_s"] = _time(jax.jit(lambda d, r, k: learning.dynamics_updates(
            cfg, d, r, k, cfg.dyn_updates)[0]), state.dyn, state.model_replay, key, reps=reps)
    if cfg.hierarchical:
        start = jnp.asarray(T.make_env(cfg).start, jnp.float32)
        out["refit_s"] = _time(jax.jit(lambda c: learning.refit(cfg, c)), state.chain, reps=reps)
        out["grow_chain_s"] = _time(jax.jit(lambda c: learning.grow_chain(cfg, c, start)), state.chain,
                                    reps=reps)
        out["chain_metrics_s"] = _time(jax.jit(lambda c: acting.chain_metrics(cfg, c, start)),
                                       state.chain, reps=reps)
    checked = [state.td3, state.dyn] + ([state.chain.clf] if cfg.hierarchical else [])
    out["finite_checks_s"] = _time(jax.jit(lambda ts: [learning.all_finite(x) for x in ts]), checked,
                                   reps=reps)
    return out


def profile(env_name: str, algo: str, B: int, overrides: dict, reps: int,
            td3_blocks=(), parts: bool = False, trained: int = 0, chained: int = 0) -> dict:
    import jax
    import jax.numpy as jnp

    from dscpp_jax import acting, learning
    from dscpp_jax import trainer as T
    from dscpp_jax.config import preset

    cfg = preset("fast", env_name, algo, num_envs=B, **overrides).validate()
    env = T.make_env(cfg)
    Tn = cfg.run.steps_per_iter
    t0 = time.perf_counter()
    state = T.init(jax.random.PRNGKey(0), cfg)
    jax.block_until_ready(state)
    t_init = time.perf_counter() - t0
    t0 = time.perf_counter()
    lowered = T.train_step.lower(state)   # trace + lower, then XLA's compile (or a cache load)
    t1 = time.perf_counter()
    lowered.compile()
    t_lower, t_compile = t1 - t0, time.perf_counter() - t1
    m = {}
    for _ in range(trained):   # real iterations: filled buffers, a grown chain
        state, m = T.train_step(state)
    jax.block_until_ready(state)
    post = state.replace(counters=state.counters.replace(
        episodes=jnp.maximum(state.counters.episodes, cfg.task.warmup_episodes),
        warmup_done=jnp.asarray(True)))

    @jax.jit
    def env_only(es, key):
        def body(es, k):
            a = jax.random.uniform(k, (B, env.action_size), jnp.float32, -1.0, 1.0)
            return jax.vmap(env.step)(es, a), None
        return jax.lax.scan(body, es, jax.random.split(key, Tn))[0]

    out = {"num_envs": B, "steps_per_iter": Tn, "init_s": t_init, "trained_iterations": trained,
           "train_step_lower_s": t_lower, "train_step_compile_s": t_compile}
    if "options/num_options" in m:
        out["options"] = int(m["options/num_options"])
    k = jax.random.PRNGKey(1)
    out["env_s"] = _time(env_only, state.env_state, k, reps=reps)
    if cfg.model_based:
        vf = acting.value_fn(cfg, state.td3) if cfg.uses_value_in_mpc else None
        vn = acting.value_net(cfg, state.td3) if cfg.uses_value_in_mpc else None
        mpc = jax.jit(lambda d, kk, o, g: acting.mpc_actions(cfg, d, kk, o, g, vf, vn))
        obs = state.env_state.obs
        goals = jnp.broadcast_to(jnp.asarray(env.goal, jnp.float32), (B, 2))
        out["mpc_decision_s"] = _time(mpc, state.dyn, k, obs, goals, reps=reps)
        out["mpc_s"] = out["mpc_decision_s"] * Tn
    roll = jax.jit(T.rollout)
    out["rollout_warmup_s"] = _time(roll, state, k, reps=reps)
    out["rollout_policy_s"] = _time(roll, post, k, reps=reps)
    learn = jax.jit(T.learn)
    out["learn_s"] = _time(learn, post, k, reps=reps)
    from dscpp_jax.td3 import td3_updates
    tcfg, sample = TD3Config.from_section(cfg.td3, cfg.model_based), T.td3_sample_fn(cfg, env)
    out["td3_updates"] = cfg.td3_updates
    out["td3_sample_block"] = cfg.td3.sample_block
    for blk in sorted({cfg.td3.sample_block, *td3_blocks}):
        fn = jax.jit(lambda td3, rep, kk, blk=blk: td3_updates(
            tcfg, td3, T.td3_buffer(cfg, rep), kk, cfg.td3_updates, sample, sample_block=blk))
        t = _time(fn, post.td3, post.replay, k, reps=reps)
        out.setdefault("td3_s_by_sample_block", {})[str(blk)] = t
        if blk == cfg.td3.sample_block:
            out["td3_s"] = t
    # learn as training meets it: right after a rollout, whose option executions left rows dirty
    rolled = roll(post, k)[0]
    out["dirty_rows_after_rollout"] = int(jnp.sum(rolled.chain.dirty)) if cfg.hierarchical else 0
    out["learn_after_rollout_s"] = _time(learn, rolled, k, reps=reps)
    if parts:
        out["learn_parts"] = learn_parts(cfg, rolled, k, reps)
    out["train_step_s"] = _time(T.train_step, post, reps=reps)
    if chained:   # as `train`'s loop runs it: each call on the state the last one returned
        s, ts = state, []
        for _ in range(chained):
            t0 = time.perf_counter()
            s, m = T.train_step(s)
            jax.device_get(m)
            ts.append(time.perf_counter() - t0)
        out["chained_train_step_s"] = statistics.median(ts)
        out["chained_train_step_each_s"] = [round(t, 4) for t in ts]
    n = B * Tn
    out["env_steps_per_s"] = {name: n / out[name] for name in
                              ("env_s", "rollout_warmup_s", "rollout_policy_s", "train_step_s")}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="u_maze")
    p.add_argument("--algo", default="mb_dscpp")
    p.add_argument("--num-envs", type=int, nargs="+", default=[128, 512])
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--td3-blocks", type=int, nargs="*", default=[],
                   help="also time the TD3 steps with these td3_sample_block values")
    p.add_argument("--learn-parts", action="store_true",
                   help="also time each part of learn alone (see above)")
    p.add_argument("--trained", type=int, default=0, metavar="N",
                   help="time on the state after N real training iterations (default 0: fresh)")
    p.add_argument("--chained", type=int, default=0, metavar="N",
                   help="also time N iterations one after another, each on the state the last "
                        "returned (as `train` runs them; default 0: none)")
    p.add_argument("--xla-flags", choices=("train", "default"), default="train",
                   help="train (default): the XLA flags `train` sets (fusion autotuner off, "
                        "deterministic kernels as `train` chooses); default: XLA's own")
    p.add_argument("--compile-cache", default=None, metavar="DIR|off",
                   help="JAX's persistent compilation cache, as `train` takes it (default: "
                        "$DSCPP_JAX_COMPILE_CACHE, else JAX's setting, else ~/.cache/dscpp_jax/xla); "
                        "the step compiled ahead for its timing is then loaded, not compiled again")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if args.trained < 0 or args.chained < 0:
        p.error("--trained and --chained must be >= 0")
    if args.xla_flags == "train":   # before JAX touches a device
        from dscpp_jax import cli, runtime
        ns = argparse.Namespace(env=args.env, algo=args.algo, physics="auto", deterministic=None)
        deterministic = runtime.use_xla_flags(cli.deterministic_choice(ns))
    else:
        deterministic = "xla_gpu_deterministic_ops=true" in os.environ.get("XLA_FLAGS", "")

    import jax

    from dscpp_jax.runtime import use_compile_cache
    from dscpp_jax.config import parse_value
    cache = use_compile_cache(args.compile_cache)
    overrides = {"inband_eval_envs": 0}   # training alone unless --set asks for in-band envs
    for s in args.set:
        name, v = s.split("=", 1)
        overrides[name] = parse_value(name, v)
    d = jax.devices()[0]
    res = {"command": " ".join([os.path.basename(sys.executable)] + sys.argv),
           "device": getattr(d, "device_kind", d.platform), "jax": jax.__version__,
           "python": platform.python_version(), "env": args.env, "algo": args.algo,
           "overrides": overrides, "xla_flags": os.environ.get("XLA_FLAGS", ""),
           "deterministic_ops": deterministic, "compile_cache": cache, "results": []}
    for B in args.num_envs:
        r = profile(args.env, args.algo, B, overrides, args.reps, args.td3_blocks,
                    parts=args.learn_parts, trained=args.trained, chained=args.chained)
        res["results"].append(r)
        print(json.dumps(r), flush=True)
    print(f"\n{'B':>6} {'env':>9} {'mpc':>9} {'roll-warm':>9} {'roll-pol':>9} {'learn':>9} "
          f"{'td3':>9} {'step':>9} {'steps/s':>9}   (seconds per iteration)")
    for r in res["results"]:
        print(f"{r['num_envs']:>6} {r['env_s']:9.3f} {r.get('mpc_s', float('nan')):9.3f} "
              f"{r['rollout_warmup_s']:9.3f} {r['rollout_policy_s']:9.3f} {r['learn_s']:9.3f} "
              f"{r['td3_s']:9.3f} {r['train_step_s']:9.3f} "
              f"{r['env_steps_per_s']['train_step_s']:9.0f}")
        if "learn_parts" in r:
            print(f"{'':>6} learn after a rollout {r['learn_after_rollout_s']:.3f} s "
                  f"({r['dirty_rows_after_rollout']} rows to refit); its parts: " + ", ".join(
                f"{k[:-2]} {v:.3f} s" for k, v in r["learn_parts"].items()))
        if len(r["td3_s_by_sample_block"]) > 1:
            print(f"{'':>6} TD3 steps ({r['td3_updates']}) by td3_sample_block: " + ", ".join(
                f"{b}: {t:.3f} s" for b, t in r["td3_s_by_sample_block"].items()))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(res, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
