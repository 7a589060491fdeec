"""Seed groups: throughput of N seeds trained in one jitted program, sharded over all local devices.

    python experiments/bench_seeds.py                                   # u_maze, mb/mf_dscpp, N = 1..16
    python experiments/bench_seeds.py --env point_u_maze --seeds-list 1,2 --iters 2 --small   # CPU smoke

For each algorithm and group size N it builds the group (`dscpp_jax.init_group`), times the
compilation of the group step (lower + compile), then, starting past the warm-up (the policy acts:
MPC or the actor, as in most of a run), runs `--iters` iterations and takes the
median time of those after the first as the steady-state time per iteration. It reports env
steps/s summed over the seeds, per seed, the compile time and the speed-up of the summed rate over
N = 1, with the devices used. A group size that fails (out of memory, or not a multiple of the
device count) is recorded with its error and the others go on.

Writes JSON (device, versions, command, every number) and a markdown table next to it.
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import statistics
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

SMALL = dict(num_envs=4, steps_per_iter=20, episode_length=100, warmup_episodes=2, max_options=4,
             max_pos_traj=8, max_neg=8, buffer_len=10, option_timeout=40, gestation=2,
             td3_hidden=32, td3_batch_size=32, td3_updates_per_step=0.1, replay_capacity=2000,
             model_capacity=2000, dyn_hidden=16, dyn_batch_size=32, dyn_updates_per_step=0.05,
             dyn_pretrain_steps=5, mpc_samples=32, mpc_horizon=3, eval_episodes=2)


def bench_one(cfg, n: int, iters: int, num_devices: int = 0) -> dict:
    """One group size on the first `num_devices` local devices (0: all of them)."""
    import jax

    from dscpp_jax import seed_group as SG
    devices = jax.local_devices()
    mesh = SG.seed_mesh(devices[:num_devices] if num_devices else devices)
    from dscpp_jax.trainer import resolve_physics
    rec = {"algo": cfg.algo, "N": n, "devices": int(mesh.size),
           "physics": resolve_physics(cfg).task.physics}
    try:
        SG.check_group_size(n, mesh)
        t0 = time.perf_counter()
        states = SG.init_group(range(n), cfg, mesh)
        # past the warm-up: the policy (MPC or the actor) acts, as in most of a run
        c = states.counters
        states = states.replace(counters=c.replace(
            episodes=c.episodes + 10 ** 6, warmup_done=c.warmup_done | True))
        jax.block_until_ready(states)
        rec["init_s"] = time.perf_counter() - t0
        fn, states, active = SG.group_step_program(states, mesh)
        t0 = time.perf_counter()
        compiled = fn.lower(states, active).compile()
        rec["compile_s"] = time.perf_counter() - t0
        times = []
        for _ in range(iters):
            t0 = time.perf_counter()
            states, m = compiled(states, active)
            jax.block_until_ready((states, m))
            times.append(time.perf_counter() - t0)
        steady = times[1:] or times
        it_s = statistics.median(steady)
        rec.update(iteration_s=it_s, iteration_times_s=times,
                   env_steps_per_s=n * cfg.steps_per_iteration_total / it_s,
                   env_steps_per_s_per_seed=cfg.steps_per_iteration_total / it_s)
        del states, m, compiled
    except Exception as e:  # noqa: BLE001 - one size failing (e.g. out of memory) is a result
        rec["error"] = f"{type(e).__name__}: {str(e).splitlines()[0][:300] if str(e) else ''}"
    gc.collect()
    return rec


def table(records: list) -> str:
    """Markdown table. The last column compares a row with the same algorithm at the same seeds per
    device on one device (present when several device counts were measured)."""
    multi = len({r["devices"] for r in records}) > 1
    head = ("| algo | N | devices | env steps/s (all seeds) | per seed | s / iteration | compile s "
            "| speed-up vs N=1 |" + (" vs 1 device, same seeds per device |" if multi else ""))
    lines = [head, "|---|---|---|---|---|---|---|---|" + ("---|" if multi else "")]
    ok = [r for r in records if "error" not in r]
    base = {r["algo"]: r["env_steps_per_s"] for r in ok if r["N"] == 1 and r["devices"] == 1}
    base.update({r["algo"]: r["env_steps_per_s"] for r in ok
                 if r["N"] == 1 and r["algo"] not in base})
    one_dev = {(r["algo"], r["N"]): r["env_steps_per_s"] for r in ok if r["devices"] == 1}
    for r in records:
        if "error" in r:
            lines.append(f"| {r['algo']} | {r['N']} | {r['devices']} | failed: {r['error']} "
                         f"| | | | |" + (" |" if multi else ""))
            continue
        b = base.get(r["algo"])
        sp = f"{r['env_steps_per_s'] / b:.2f}x" if b else "-"
        row = (f"| {r['algo']} | {r['N']} | {r['devices']} | {r['env_steps_per_s']:,.0f} | "
               f"{r['env_steps_per_s_per_seed']:,.0f} | {r['iteration_s']:.3f} | "
               f"{r['compile_s']:.1f} | {sp} |")
        if multi:
            same = one_dev.get((r["algo"], r["N"] // r["devices"]))
            row += (f" {r['env_steps_per_s'] / same:.2f}x |"
                    if same and r["N"] % r["devices"] == 0 else " - |")
        lines.append(row)
    return "\n".join(lines)


def as_train(args) -> argparse.Namespace:
    """The `train` command whose `--deterministic` default the benchmark takes (it follows the
    physics): set once, before JAX starts, for every algorithm and group size of the run."""
    return argparse.Namespace(env=args.env, set=args.set, physics=None,
                              deterministic=args.deterministic)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="u_maze")
    p.add_argument("--algos", default="mb_dscpp,mf_dscpp")
    p.add_argument("--seeds-list", default="1,2,4,8,16",
                   help="group sizes N (seeds per device with --per-device)")
    p.add_argument("--devices-list", default=None,
                   help="numbers of local devices to shard each group over, e.g. 1,2: the "
                        "one-device baseline and the multi-device rows in one run (default: all)")
    p.add_argument("--per-device", action="store_true",
                   help="--seeds-list counts seeds per device: N = seeds x devices")
    p.add_argument("--iters", type=int, default=5, help="iterations per N (the first is dropped)")
    p.add_argument("--preset", default="fast")
    p.add_argument("--small", action="store_true", help="tiny sizes (CPU smoke test)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="override a Config field (repeatable)")
    p.add_argument("--deterministic", action=argparse.BooleanOptionalAction, default=None,
                   help="--xla_gpu_deterministic_ops on or off (default: as `train` chooses: "
                        "off where the ant physics is MuJoCo Warp)")
    p.add_argument("--out", default=None,
                   help="JSON path (default experiments/results/bench_seeds_<device>.json)")
    args = p.parse_args(argv)

    from dscpp_jax.cli import deterministic_choice, parse_overrides
    from dscpp_jax.runtime import use_xla_flags
    det = use_xla_flags(deterministic_choice(as_train(args)))
    import jax

    from dscpp_jax.config import preset
    from dscpp_jax.run_logging import library_versions
    # training alone, as the recorded figures: no in-band evaluation unless --set asks for it
    kw = dict(SMALL, inband_eval_envs=0) if args.small else {"inband_eval_envs": 0}
    kw.update(parse_overrides(args.set))
    sizes = [int(x) for x in args.seeds_list.split(",") if x.strip()]
    n_local = len(jax.local_devices())
    dev_counts = ([int(x) for x in args.devices_list.split(",") if x.strip()]
                  if args.devices_list else [n_local])
    bad = [k for k in dev_counts if not 1 <= k <= n_local]
    if bad:
        p.error(f"--devices-list {args.devices_list}: this host has {n_local} local device(s)")
    dev = jax.local_devices()[0]
    kind = getattr(dev, "device_kind", dev.platform).replace(" ", "_")
    out = args.out or os.path.join(ROOT, "experiments", "results", f"bench_seeds_{kind}.json")
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    md = os.path.splitext(out)[0] + ".md"
    payload = {"command": " ".join([os.path.basename(sys.executable)] + sys.argv),
               "env": args.env, "preset": args.preset, "small": args.small, "overrides": kw,
               "iters": args.iters, "deterministic_gpu_ops": det,
               "devices": [str(d) for d in jax.local_devices()], "platform": platform.platform(),
               "versions": library_versions(), "results": []}

    def write() -> str:   # after every group size: a run cut short keeps what it measured
        with open(out, "w") as f:
            json.dump(payload, f, indent=1)
        text = (f"# Seed groups: {args.env}, preset {args.preset}{' (small)' if args.small else ''}"
                f"\n\nDevices: {', '.join(payload['devices'])}\n\n{table(payload['results'])}\n\n"
                f"Command: `{payload['command']}`\n")
        with open(md, "w") as f:
            f.write(text)
        return text

    for algo in [a.strip() for a in args.algos.split(",") if a.strip()]:
        cfg = preset(args.preset, args.env, algo, **kw).validate()
        for k in dev_counts:
            for s in sizes:
                n = s * k if args.per_device else s
                rec = bench_one(cfg, n, max(1, args.iters), k)
                payload["results"].append(rec)
                print(json.dumps(rec), flush=True)
                text = write()
    print(text)
    print(f"wrote {out} and {md}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
