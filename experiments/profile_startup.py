"""Where a training run's first seconds go: the process start before the first iteration ends.

Times, in one fresh process and in the order `dscpp_jax.cli train` does them: the imports, the
accelerator's start, building the env, compiling `init` ahead (a cache hit when the persistent XLA
cache holds it) while Warp's kernel build starts in a thread, tracing, lowering and compiling
`train_step`, what is left of Warp's kernel build, running `init`, and the first iteration. Run it twice on the same cache directory to see a cold and a warm start:

    python experiments/profile_startup.py --env u_maze --algo mb_dscpp --out cold.json
    python experiments/profile_startup.py --env u_maze --algo mb_dscpp --out warm.json

Prints a table and writes JSON (`--out`). `--set field=value` as in `train`; `--cprofile DIR`
also profiles each phase (after the imports) into DIR/<phase>.prof for `python -m pstats`.
"""
from __future__ import annotations

import time

T_PROCESS = time.time()

import argparse  # noqa: E402
import contextlib  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="u_maze")
    p.add_argument("--algo", default="mb_dscpp")
    p.add_argument("--preset", default="fast")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    p.add_argument("--compile-cache", default=None,
                   help="persistent XLA cache (default: as train: $DSCPP_JAX_COMPILE_CACHE, ...)")
    p.add_argument("--deterministic", action=argparse.BooleanOptionalAction, default=None,
                   help="deterministic XLA GPU kernels; default as `train` chooses (part of the "
                        "compile cache's key: profile what `train` will load)")
    p.add_argument("--cprofile", default=None, metavar="DIR",
                   help="also profile each phase after the imports with cProfile (main thread) "
                        "into DIR/<phase>.prof")
    p.add_argument("--until", default=None, choices=("init", "lower"),
                   help="stop after this phase (e.g. to profile the start-up without compiling)")
    p.add_argument("--out", default=None, help="write the timings as JSON here")
    args = p.parse_args(argv)

    phases: dict[str, float] = {}
    t = time.time()
    phases["interpreter to script"] = t - T_PROCESS   # ~0 unless the caller measures from exec

    import jax
    from dscpp_jax import preset
    from dscpp_jax import trainer as T
    from dscpp_jax.cli import deterministic_choice
    from dscpp_jax.runtime import use_compile_cache, use_xla_flags
    from dscpp_jax.config import parse_value
    phases["imports"] = time.time() - t
    deterministic = use_xla_flags(deterministic_choice(args))
    if args.cprofile:
        os.makedirs(args.cprofile, exist_ok=True)

    @contextlib.contextmanager
    def phase(name: str):
        """Time one phase (and with --cprofile, profile it into DIR/<phase>.prof)."""
        prof = None
        if args.cprofile:
            import cProfile
            prof = cProfile.Profile()
            prof.enable()
        t0 = time.time()
        yield
        phases[name] = time.time() - t0
        if prof is not None:
            prof.disable()
            slug = "".join(c if c.isalnum() else "_" for c in name.split(" (")[0]).strip("_")
            prof.dump_stats(os.path.join(args.cprofile, f"{slug}.prof"))

    with phase("accelerator start (jax.devices)"):
        cache = use_compile_cache(args.compile_cache)
        devices = jax.devices()

    overrides = {}
    for item in args.set:
        if "=" not in item:
            raise SystemExit(f"--set {item!r}: write FIELD=VALUE")
        k, v = item.split("=", 1)
        overrides[k] = parse_value(k, v)
    cfg = preset(args.preset, env=args.env, algo=args.algo, seed=args.seed, **overrides)
    cfg = T.resolve_physics(cfg.validate())

    with phase("env build"):
        T.make_env(cfg)
    key = jax.random.PRNGKey(cfg.run.seed)
    if args.until == "init":
        with phase("init (compile or cache load, run)"):
            jax.block_until_ready(T.init(key, cfg))
    else:
        _step_phases(args, phase, T, cfg, key)

    total = time.time() - T_PROCESS
    last = "second iteration" if args.until is None else f"train_step {args.until}" \
        if args.until == "lower" else args.until
    out = {"env": args.env, "algo": args.algo, "preset": args.preset, "physics": cfg.task.physics,
           "deterministic_ops": deterministic,
           "backend": jax.default_backend(), "device": str(devices[0].device_kind),
           "jax": jax.__version__, "compile_cache": cache,
           "phases_s": {k: round(v, 3) for k, v in phases.items()},
           f"process to end of {last}_s": round(total, 3)}
    w = max(len(k) for k in phases)
    print(f"{args.env} {args.algo} ({cfg.task.physics} physics, {out['device']}, cache {cache})")
    for k, v in phases.items():
        print(f"  {k:<{w}}  {v:7.2f} s")
    print(f"  {'process start to end of ' + last:<{w}}  {total:7.2f} s")
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)
    return out


def _step_phases(args, phase, T, cfg, key) -> None:
    """As `train` does on MuJoCo Warp: Warp's kernel build starts in a thread while XLA compiles
    `init` and `train_step` ahead of time (`trainer.compile_ahead`, here split into its parts);
    then `init` runs and two iterations (each timed)."""
    import jax
    cfg_dev = T.resolve_physics(cfg.validate()).device_view()
    with phase("init: compile or cache load (ahead)"):
        prewarm = T.prewarm_physics(cfg)
        T.init_jit.lower(key, cfg_dev).compile()
    with phase("train_step: trace"):
        traced = T.train_step.trace(jax.eval_shape(T.init_jit, key, cfg_dev))
    with phase("train_step: lower"):
        lowered = traced.lower()
    if args.until == "lower":
        if prewarm is not None:
            prewarm.join()
        return
    with phase("train_step: compile or cache load"):
        compiled = lowered.compile()
    with phase("Warp kernels (left after the compiles)"):
        if prewarm is not None:
            prewarm.join()
    with phase("init (run)"):
        state = T.init(key, cfg)
        jax.block_until_ready(state)
    with phase("first iteration (run)"):
        state, m = compiled(state)
        jax.block_until_ready(m)
    with phase("second iteration (run)"):
        state, m = compiled(state)
        jax.block_until_ready(m)


if __name__ == "__main__":
    main()
