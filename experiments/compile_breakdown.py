"""Where the start of a training run goes: imports, env build, `init`, tracing and XLA compile of
`train_step`, MuJoCo Warp's kernel build (at its first launch) and the first iterations.

    python experiments/compile_breakdown.py --env u_maze --algo mb_dscpp --out compile.json
    python experiments/compile_breakdown.py ... --prewarm   # Warp's kernels build during the compile

Run it in a fresh process on empty caches for the cold figures (remove the directory of
DSCPP_JAX_COMPILE_CACHE or pass --compile-cache off, and ~/.cache/warp), and again for the warm
ones. The first call's time less the second's is what the first launch costs beyond a normal
iteration: on MuJoCo Warp, mostly building its GPU kernels.
"""
import argparse
import json
import os
import sys
import time

T0 = time.time()
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="u_maze")
    p.add_argument("--algo", default="mb_dscpp")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--compile-cache", default=None, help="as train's --compile-cache")
    p.add_argument("--prewarm", action="store_true",
                   help="build Warp's kernels in a thread while XLA compiles, as train does")
    p.add_argument("--iterations", type=int, default=3)
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)

    import jax

    from dscpp_jax import trainer as T
    from dscpp_jax.cli import parse_overrides
    from dscpp_jax.runtime import use_compile_cache
    from dscpp_jax.config import preset
    use_compile_cache(a.compile_cache)
    t = {"imports_s": time.time() - T0}
    cfg = T.resolve_physics(preset("fast", a.env, a.algo, **parse_overrides(a.set)).validate())
    s = time.time()
    T.make_env(cfg)
    T.step_env(cfg)
    t["env_build_s"] = time.time() - s
    thread = T.prewarm_physics(cfg) if a.prewarm else None
    s = time.time()
    state = jax.block_until_ready(T.init(jax.random.PRNGKey(0), cfg))
    t["init_s"] = time.time() - s
    s = time.time()
    lowered = T.train_step.lower(state)
    t["trace_lower_s"] = time.time() - s
    s = time.time()
    lowered.compile()
    t["xla_compile_s"] = time.time() - s
    if thread is not None:
        s = time.time()
        thread.join()
        t["prewarm_wait_s"] = time.time() - s
    calls = []
    for _ in range(a.iterations):
        s = time.time()
        state, m = T.train_step(state)
        jax.block_until_ready(m)
        calls.append(time.time() - s)
    t["first_call_s"] = calls[0]
    t["later_calls_s"] = calls[1:]
    t["first_launch_extra_s"] = calls[0] - (min(calls[1:]) if len(calls) > 1 else 0.0)
    t["process_s"] = time.time() - T0
    out = {"env": a.env, "algo": a.algo, "physics": cfg.task.physics, "prewarm": thread is not None,
           "inband_eval_envs": cfg.eval.inband_envs, "device": str(jax.devices()[0].device_kind),
           "jax": jax.__version__, "seconds": {k: (round(v, 2) if isinstance(v, float) else
                                                    [round(x, 2) for x in v]) for k, v in t.items()}}
    print(json.dumps(out, indent=1))
    if a.out:
        with open(a.out, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
