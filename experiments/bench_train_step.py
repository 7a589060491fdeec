"""Time the whole jitted train step: compile time and steady-state seconds per iteration, for one
seed or a seed group (`trainer.train_step_group_impl`), per physics back end.

    python experiments/bench_train_step.py --env u_maze --algos mb_dscpp mf_dscpp \
        --physics jax warp --seeds 1 8 --iters 5 --out bench.json
    python experiments/bench_train_step.py --env point_u_maze --seeds 1 2 --iters 2 --small  # CPU

Each case starts past the warm-up (the policy acts: MPC or the actor), so the timed iterations are
the ones that dominate a run. `--repeat` also runs each case a second time from the same state and
reports whether every metric and the final state repeat bit for bit. Writes JSON with the device,
versions and command; one failing case (e.g. out of memory) is recorded, not fatal.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
import traceback

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

SMALL = dict(num_envs=8, steps_per_iter=10, mpc_samples=64, dyn_hidden=32, td3_hidden=32,
             max_options=6, replay_capacity=20_000, model_capacity=20_000, dyn_pretrain_steps=5)


def run_case(env, algo, physics, n_seeds, iters, overrides, repeat):
    import jax
    import jax.numpy as jnp
    import numpy as np

    from dscpp_jax import trainer as T
    from dscpp_jax.config import preset

    cfg = preset("fast", env, algo, physics=physics, group_size=n_seeds, **overrides)
    cfg = T.resolve_physics(cfg.validate()).device_view()
    keys = jnp.stack([jax.random.PRNGKey(s) for s in range(n_seeds)])
    if n_seeds == 1:
        state = T.init(keys[0], cfg)
        step = T.train_step
    else:
        state = jax.jit(jax.vmap(lambda k: T.init_impl(k, cfg)))(keys)
        step = jax.jit(T.train_step_group_impl)
    # past the warm-up: the policy (MPC / actor) acts from the first timed step
    c = state.counters
    state = state.replace(counters=c.replace(episodes=jnp.full_like(c.episodes, 10 ** 6),
                                             warmup_done=jnp.ones_like(c.warmup_done)))
    jax.block_until_ready(state)
    t0 = time.perf_counter()
    compiled = step.lower(state).compile()
    t_compile = time.perf_counter() - t0
    s, times, ms = state, [], []
    for _ in range(iters):
        t0 = time.perf_counter()
        s, m = compiled(s)
        jax.block_until_ready(m)
        times.append(time.perf_counter() - t0)
        ms.append(m)
    it_s = statistics.median(times[1:] if len(times) > 1 else times)
    steps = n_seeds * cfg.run.num_envs * cfg.run.steps_per_iter
    out = dict(env=env, algo=algo, physics=cfg.task.physics, seeds=n_seeds, num_envs=cfg.run.num_envs,
               steps_per_iter=cfg.run.steps_per_iter, compile_s=t_compile, iteration_s=it_s,
               iteration_times=times, env_steps_per_s=steps / it_s,
               env_steps_per_s_per_seed=steps / it_s / n_seeds,
               overflow_steps=float(np.sum([np.sum(np.asarray(m["train/physics_overflow_steps"]))
                                            for m in ms])))
    if repeat:
        s2 = state
        ms2 = []
        for _ in range(iters):
            s2, m2 = compiled(s2)
            ms2.append(m2)
        same_m = all(bool(np.array_equal(np.asarray(a[k]), np.asarray(b[k]), equal_nan=True))
                     for a, b in zip(ms, ms2) for k in a)
        la, lb = jax.tree_util.tree_leaves(s), jax.tree_util.tree_leaves(s2)
        same_s = all(bool(np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True))
                     for a, b in zip(la, lb))
        diff = max(float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))))
                   for a, b in zip(la, lb) if np.issubdtype(np.asarray(a).dtype, np.floating)
                   and np.asarray(a).size)
        out.update(repeat_metrics_identical=same_m, repeat_state_identical=same_s,
                   repeat_state_max_abs_diff=diff)
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env", default="u_maze")
    p.add_argument("--algos", nargs="+", default=["mb_dscpp", "mf_dscpp"])
    p.add_argument("--physics", nargs="+", default=["auto"])
    p.add_argument("--seeds", nargs="+", type=int, default=[1])
    p.add_argument("--iters", type=int, default=5)
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--small", action="store_true", help="tiny sizes (CPU smoke test)")
    p.add_argument("--repeat", action="store_true", help="check that a second run repeats")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)

    import jax

    from dscpp_jax.config import parse_value
    # training alone unless --set asks for in-band evaluation envs
    overrides = dict(SMALL, inband_eval_envs=0) if args.small else {"inband_eval_envs": 0}
    for kv in args.set:
        k, v = kv.split("=", 1)
        overrides[k] = parse_value(k, v)
    dev = jax.devices()[0]
    rows = []
    for algo in args.algos:
        for physics in args.physics:
            for n in args.seeds:
                try:
                    r = run_case(args.env, algo, physics, n, args.iters, overrides, args.repeat)
                except Exception as e:  # noqa: BLE001  (one failing case must not end the sweep)
                    r = dict(env=args.env, algo=algo, physics=physics, seeds=n,
                             error=f"{type(e).__name__}: {str(e)[:500]}")
                    traceback.print_exc()
                rows.append(r)
                print(json.dumps({k: v for k, v in r.items() if k != "iteration_times"}),
                      flush=True)
    import mujoco
    result = dict(command=" ".join([os.path.basename(sys.executable)] + sys.argv),
                  device=str(getattr(dev, "device_kind", dev.platform)),
                  num_devices=jax.device_count(), jax=jax.__version__, mujoco=mujoco.__version__,
                  python=platform.python_version(), rows=rows)
    print("| algo | physics | seeds | compile s | s/iteration | env steps/s | per seed |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            print(f"| {r['algo']} | {r['physics']} | {r['seeds']} | error: {r['error'][:60]} |")
        else:
            print(f"| {r['algo']} | {r['physics']} | {r['seeds']} | {r['compile_s']:.1f} | "
                  f"{r['iteration_s']:.3f} | {r['env_steps_per_s']:,.0f} | "
                  f"{r['env_steps_per_s_per_seed']:,.0f} |")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
