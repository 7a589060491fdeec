"""Env throughput: MJX ant mazes (batched, jitted step in lax.scan, random actions) vs MuJoCo C.

For each layout and batch size: reset a batch, compile a `lax.scan` of `--steps` env steps (5
physics frames each, random actions drawn inside the scan), time `--repeats` calls and report the
best as env steps/s. In the same run, single-core MuJoCo C (`mujoco.mj_step`) steps the identical
MjModel with random controls. Prints a table and writes JSON to experiments/results/.

    python experiments/bench_env.py                       # all layouts, batches 1..16384
    python experiments/bench_env.py --layouts u_maze --batches 1,64 --steps 20   # small (CPU)
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import importlib.metadata
import json
import os
import platform
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from dscpp_jax import envs  # noqa: E402

DEFAULT_LAYOUTS = "u_maze,four_rooms,medium,large,ant_reacher"
DEFAULT_BATCHES = "1,16,256,1024,4096,16384"


def _version(pkg):
    try:
        return importlib.metadata.version(pkg)
    except importlib.metadata.PackageNotFoundError:
        return None


def make_runner(env, batch: int, steps: int):
    def run(states, key):
        def body(carry, _):
            s, k = carry
            k, ka = jax.random.split(k)
            a = jax.random.uniform(ka, (batch, env.action_size), minval=-1.0, maxval=1.0)
            return (jax.vmap(env.step)(s, a), k), None

        (states, key), _ = jax.lax.scan(body, (states, key), None, length=steps)
        return states
    return jax.jit(run, donate_argnums=0)


def bench_mjx(env, batch, steps, repeats, seed=0):
    keys = jax.random.split(jax.random.key(seed), batch)
    states = jax.jit(jax.vmap(env.reset))(keys)
    run = make_runner(env, batch, steps)
    t0 = time.perf_counter()
    states = run(states, jax.random.key(seed + 1))
    jax.block_until_ready(states.obs)
    compile_s = time.perf_counter() - t0
    times = []
    for r in range(repeats):
        t0 = time.perf_counter()
        states = run(states, jax.random.key(seed + 2 + r))
        jax.block_until_ready(states.obs)
        times.append(time.perf_counter() - t0)
    best = min(times)
    nan_frac = float(jnp.mean(states.info["nan"]))
    return {"batch": batch, "steps_per_call": steps, "compile_plus_first_s": compile_s,
            "times_s": times, "env_steps_per_s": batch * steps / best,
            "physics_steps_per_s": batch * steps * env.config.frame_skip / best,
            "ms_per_batched_env_step": 1e3 * best / steps, "nan_fraction_end": nan_frac}


def bench_mujoco_c(env, env_steps, seed=0):
    """Single-core MuJoCo C on the same ant and walls. With proxy walls the MJCF's merged wall boxes
    are made to collide instead (MuJoCo C has its own broad phase, so this is its fast path)."""
    if getattr(env, "uses_proxies", False):
        env = type(env)(env.layout, dataclasses.replace(env.config, wall_mode="static"))
    m = env.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = m.qpos0
    rng = np.random.default_rng(seed)
    ctrl = rng.uniform(-1.0, 1.0, (env_steps, m.nu))
    t0 = time.perf_counter()
    for i in range(env_steps):
        d.ctrl[:] = ctrl[i]
        mujoco.mj_step(m, d, env.config.frame_skip)
    dt = time.perf_counter() - t0
    return {"env_steps": env_steps, "env_steps_per_s": env_steps / dt,
            "physics_steps_per_s": env_steps * env.config.frame_skip / dt}


def contact_sizes(env):
    d = env.reset(jax.random.key(0)).pipeline_state
    return {"contact_slots": int(d._impl.contact.geom.shape[0]),
            "constraint_rows": int(d._impl.efc_J.shape[0]),
            "wall_boxes": len(env.layout.wall_boxes), "ngeom": int(env.mj_model.ngeom)}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--layouts", default=DEFAULT_LAYOUTS, help="comma-separated ant layouts")
    p.add_argument("--batches", default=DEFAULT_BATCHES, help="comma-separated batch sizes")
    p.add_argument("--steps", type=int, default=50, help="env steps per timed scan call")
    p.add_argument("--repeats", type=int, default=2, help="timed calls per config (best kept)")
    p.add_argument("--c-steps", type=int, default=2000, help="MuJoCo C env steps per layout")
    p.add_argument("--integrator", default=None, help="override the integrator (Euler|RK4)")
    p.add_argument("--override", action="append", default=[],
                   help="extra env override key=value (int/float/str), repeatable")
    p.add_argument("--time-budget", type=float, default=330.0,
                   help="seconds; configs left when it runs out are skipped (and listed)")
    p.add_argument("--out", default=None, help="JSON path (default experiments/results/bench_env_<device>.json)")
    args = p.parse_args(argv)

    overrides = {}
    if args.integrator:
        overrides["integrator"] = args.integrator
    for kv in args.override:
        k, v = kv.split("=", 1)
        for cast in (int, float):
            try:
                v = cast(v)
                break
            except ValueError:
                pass
        overrides[k] = v
    layouts = [s for s in args.layouts.split(",") if s]
    batches = [int(b) for b in args.batches.split(",") if b]
    dev = jax.devices()[0]
    device = f"{dev.platform}:{getattr(dev, 'device_kind', '?')}"
    t_start = time.perf_counter()
    out = args.out or os.path.join(os.path.dirname(os.path.abspath(__file__)), "results",
                                   f"bench_env_{dev.platform}.json")
    record = {
        "command": "python " + " ".join([os.path.relpath(sys.argv[0])] + sys.argv[1:]),
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "device": device, "num_devices": jax.device_count(), "host": platform.processor() or platform.machine(),
        "versions": {k: _version(k) for k in ("jax", "jaxlib", "mujoco", "mujoco-mjx", "brax", "numpy")},
        "python": platform.python_version(), "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "overrides": overrides, "steps_per_call": args.steps, "repeats": args.repeats,
        "layouts": {}, "skipped": [],
    }
    print(f"device {device}; jax {record['versions']['jax']}, mujoco {record['versions']['mujoco']}, "
          f"mjx {record['versions']['mujoco-mjx']}", flush=True)

    def save():
        os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
        with open(out, "w") as f:
            json.dump(record, f, indent=1)

    for name in layouts:
        env = envs.make(name, **overrides)
        cfg = env.config
        entry = {"config": {"integrator": cfg.integrator, "timestep": cfg.timestep,
                            "frame_skip": cfg.frame_skip, "solver_iterations": cfg.solver_iterations,
                            "ls_iterations": cfg.ls_iterations, "jacobian": cfg.jacobian,
                            "wall_contacts": cfg.wall_contacts, "wall_mode": cfg.wall_mode,
                            "uses_proxies": bool(getattr(env, "uses_proxies", False))},
                 **contact_sizes(env), "mujoco_c": bench_mujoco_c(env, args.c_steps), "mjx": []}
        record["layouts"][name] = entry
        c = entry["mujoco_c"]["env_steps_per_s"]
        print(f"{name}: MuJoCo C 1 core {c:,.0f} env steps/s; contact slots {entry['contact_slots']}, "
              f"constraint rows {entry['constraint_rows']}", flush=True)
        for b in batches:
            if time.perf_counter() - t_start > args.time_budget:
                record["skipped"].append([name, b])
                print(f"  skip batch {b} (time budget)", flush=True)
                continue
            r = bench_mjx(env, b, args.steps, args.repeats)
            r["speedup_vs_mujoco_c_1core"] = r["env_steps_per_s"] / c
            entry["mjx"].append(r)
            print(f"  batch {b:6d}: {r['env_steps_per_s']:>12,.0f} env steps/s  "
                  f"({r['ms_per_batched_env_step']:.2f} ms/step, {r['speedup_vs_mujoco_c_1core']:.1f}x C, "
                  f"compile {r['compile_plus_first_s']:.0f}s)", flush=True)
            save()
        save()
    record["total_s"] = time.perf_counter() - t_start
    save()

    print("\n| layout | batch | env steps/s | x MuJoCo C (1 core) |")
    print("|---|---:|---:|---:|")
    for name, e in record["layouts"].items():
        print(f"| {name} (C: {e['mujoco_c']['env_steps_per_s']:,.0f}/s) | | | |")
        for r in e["mjx"]:
            print(f"| {name} | {r['batch']} | {r['env_steps_per_s']:,.0f} | {r['speedup_vs_mujoco_c_1core']:.1f} |")
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
