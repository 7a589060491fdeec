"""Where the iteration of a seed group spends its time, per component, at several group sizes.

    python experiments/profile_seed_group.py --env u_maze --algo mf_dscpp --seeds-list 1,16
    python experiments/profile_seed_group.py --env point_u_maze --algo mb_dscpp --seeds-list 1,2 --small  # CPU smoke

For each group size N it builds the group on one device (`dscpp_jax.init_group`), moves it past the
warm-up (the policy acts, as in most of a run) and times, as `bench_seeds.py` does the whole step
(median of repeated jitted calls after a first call that compiles, results blocked on), each part
of the iteration vmapped over the seeds with the seed axis named, exactly as the group step runs it:

  physics     T steps of the N x B environments with random actions (MuJoCo Warp flattens the
              seeds' worlds into one batch)
  mpc         one MPC decision of every seed (model-based algorithms; T of them per iteration)
  rollout     the whole T-step collection scan (options, policy or MPC, in-band evaluation, replay)
  learn       TD3 + dynamics updates, classifier refits, chain growth (only with --parts: compiled
              on its own it took XLA over two minutes on an H100, against ~25 s for the whole step;
              the step minus the rollout tells its time)
  td3         the TD3+HER gradient steps alone (part of learn)
  dynamics    the dynamics model's gradient steps alone (part of learn, model-based)
  step        the whole group step (`train_step_group`'s program)

`--td3-variants` times the TD3 steps again with one thing changed, to tell what bounds them
(measurements, not options of the library):
  fixed_batch   every step reuses one pre-drawn minibatch: no replay sampling or HER relabelling
  bf16_compute  TD3Config(compute_dtype="bfloat16"): bf16 products and activations in the
                hidden layers
                (a context of jax.default_matmul_precision("bfloat16") would not do it: it asks
                for the DEFAULT precision, which float32 matmuls already get)
  highest       matmuls at full float32 precision ("highest")
  half_batch    half the minibatch size

`--trace` runs every timed part once more under the JAX profiler and summarises the device's
kernels for it: how many ran, their summed time against the call's wall time (the rest is the
device waiting for launches), and the kernels (XLA ops) that took the most time, by name, each
with the JAX operation it came from. With
`--hlo-dir DIR` the optimised HLO of each part is written there, to read what a fusion holds.

Writes JSON (device, versions, command, every number) with --out.
"""
from __future__ import annotations

import argparse
import contextlib
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

VARIANTS = ("fixed_batch", "bf16_compute", "highest", "half_batch")
PARTS = ("physics", "mpc", "rollout", "learn", "td3", "dynamics", "step")
DEFAULT_PARTS = ("physics", "mpc", "rollout", "td3", "dynamics", "step")


def _time(fn, *args, reps=3):
    import jax
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))  # compile + first call
    first = time.perf_counter() - t0
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), first


def hlo_ops(hlo_text: str) -> dict:
    """Instruction name -> the JAX operation it came from (its ``op_name`` metadata), for every
    instruction of an optimised HLO module that has one. Names are keyed as kernels are named in
    a trace: with ``.`` and ``-`` as ``_`` (``gemm_fusion_dot.37`` -> ``gemm_fusion_dot_37``)."""
    import re
    pat = re.compile(r'^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=.*?metadata=\{[^}]*op_name="([^"]*)"')
    out = {}
    for line in hlo_text.splitlines():
        m = pat.match(line)
        if m:
            out.setdefault(_key(m.group(1)), m.group(2))
    return out


def _key(name: str) -> str:
    """A kernel's or instruction's name as `hlo_ops` keys it (GPU traces write `.` as `_`)."""
    import re
    return re.sub(r"[.\-]", "_", name)


def _short_op(op: str) -> str:
    """The JAX operation's path without the jit / vmap / loop-body wrappers around it."""
    cut = max(op.rfind(w) + len(w) if w in op else 0
              for w in ("eval_jaxpr/", "closed_call/", "while/body/"))
    return op[cut:] or op


def trace_summary(fn, *args, top: int = 30, hlo_text: str | None = None) -> dict:
    """One call of ``fn(*args)`` under the JAX profiler: its device kernels, summed by name.

    Returns the call's wall time, the number of kernels the device ran, their summed time, and the
    ``top`` names by summed time (per line of the device's trace: "XLA Ops" names HLO ops,
    the stream lines name kernels). On a CPU the host threads' events stand in for kernels.
    Given the program's optimised HLO (``hlo_text``), each name that is an instruction of it also
    gets ``op``: the JAX operation it came from (e.g. ``TwinCritic/vmap(heads)/hidden_1/dot_general``)."""
    ops = hlo_ops(hlo_text) if hlo_text else {}
    import glob
    import tempfile

    import jax
    from jax.profiler import ProfileData

    with tempfile.TemporaryDirectory() as d:
        with jax.profiler.trace(d):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(*args))
            wall = time.perf_counter() - t0
        files = glob.glob(os.path.join(d, "**", "*.xplane.pb"), recursive=True)
        if not files:
            return {"wall_s": wall, "error": "the profiler wrote no trace"}
        data = ProfileData.from_file(files[0])
        lines = {}
        for plane in data.planes:
            if not (plane.name.startswith("/device:") or plane.name == "/host:CPU"):
                continue
            for line in plane.lines:
                if plane.name == "/host:CPU" and not line.name.startswith("tf_XLA"):
                    continue
                agg = {}
                for ev in line.events:
                    c, t = agg.get(ev.name, (0, 0.0))
                    agg[ev.name] = (c + 1, t + ev.duration_ns)
                if not agg:
                    continue
                busy = sum(t for _, t in agg.values()) / 1e9
                count = sum(c for c, _ in agg.values())
                ranked = sorted(agg.items(), key=lambda kv: -kv[1][1])[:top]
                lines[f"{plane.name} | {line.name}"] = {
                    "events": count, "busy_s": busy,
                    "top": [dict({"name": k[:160], "count": c, "total_s": t / 1e9},
                                 **({"op": _short_op(ops[_key(k)])[:200]} if _key(k) in ops else {}))
                            for k, (c, t) in ranked]}
    return {"wall_s": wall, "lines": lines}


def _print_trace(name: str, tr: dict) -> None:
    print(f"  trace of {name}: wall {tr['wall_s']:.4f} s", flush=True)
    for lname, ln in tr.get("lines", {}).items():
        print(f"    {lname}: {ln['events']} events, busy {ln['busy_s']:.4f} s", flush=True)
        for row in ln["top"][:15]:
            op = f"  ({row['op'][:90]})" if "op" in row else ""
            print(f"      {row['total_s']:8.4f} s {row['count']:>8} x  {row['name'][:60]}{op}", flush=True)


def profile(cfg, n: int, reps: int, variants=(), parts=DEFAULT_PARTS, trace: bool = False,
            hlo_dir: str | None = None) -> dict:
    import dataclasses

    import jax
    import jax.numpy as jnp

    from dscpp_jax import acting, learning
    from dscpp_jax import seed_group as SG
    from dscpp_jax import trainer as T
    from dscpp_jax.td3 import td3_updates

    A = T.SEED_AXIS
    mesh = SG.seed_mesh(jax.local_devices()[:1])
    states = SG.init_group(range(n), cfg, mesh)
    c = states.counters
    states = states.replace(counters=c.replace(episodes=c.episodes + 10 ** 6,
                                               warmup_done=c.warmup_done | True))
    gcfg = states.config
    treedef, specs = SG._spec_key(states, n)
    axes = SG._vmap_axes(treedef, specs)
    keys = jax.random.split(jax.random.PRNGKey(1), n)
    B, Tn = gcfg.run.num_envs, gcfg.run.steps_per_iter
    out = {"N": n, "num_envs": B, "steps_per_iter": Tn, "td3_updates": gcfg.td3_updates,
           "td3_batch_size": gcfg.td3.batch_size, "td3_sample_block": gcfg.td3.sample_block,
           "first_call_s": {}}
    want = (lambda name: name in parts)

    def record(name, fn, *args):
        t, first = _time(fn, *args, reps=reps)
        out[name + "_s"] = t
        out["first_call_s"][name] = first
        print(f"  N={n:>3} {name:<22} {t:8.4f} s", flush=True)
        text = fn.lower(*args).compile().as_text() if (trace or hlo_dir) else None
        if hlo_dir:
            os.makedirs(hlo_dir, exist_ok=True)
            with open(os.path.join(hlo_dir, f"{name}_N{n}.hlo.txt"), "w") as f:
                f.write(text)
        if trace:
            tr = out.setdefault("trace", {})[name] = trace_summary(fn, *args, hlo_text=text)
            _print_trace(name, tr)

    def over_seeds(f, in_axes, out_axes):
        return jax.jit(jax.vmap(f, in_axes=in_axes, out_axes=out_axes, axis_name=A))

    env = T.make_env(gcfg)
    if want("physics"):
        def physics(es, k):
            def body(es, kk):
                a = jax.random.uniform(kk, (B, env.action_size), jnp.float32, -1.0, 1.0)
                return jax.vmap(env.step)(es, a), None
            return jax.lax.scan(body, es, jax.random.split(k, Tn))[0]
        record("physics", over_seeds(physics, (axes.env_state, 0), axes.env_state),
               states.env_state, keys)
    if gcfg.model_based and want("mpc"):
        def mpc(td3, dyn, k, obs):
            goals = jnp.broadcast_to(jnp.asarray(env.goal, jnp.float32), (B, 2))
            vf = acting.value_fn(gcfg, td3) if gcfg.uses_value_in_mpc else None
            vn = acting.value_net(gcfg, td3) if gcfg.uses_value_in_mpc else None
            return acting.mpc_actions(gcfg, dyn, k, obs, goals, vf, vn)
        record("mpc_decision", over_seeds(mpc, 0, 0), states.td3, states.dyn, keys,
               states.env_state.obs)
        out["mpc_s"] = out["mpc_decision_s"] * Tn
    if want("rollout"):
        record("rollout", over_seeds(lambda s, k: T.rollout(s, k, A), (axes, 0), (axes, 0)),
               states, keys)
    if want("learn"):
        record("learn", over_seeds(lambda s, k: T.learn(s, k, A), (axes, 0), (axes, 0)),
               states, keys)
    tcfg, sample = TD3Config.from_section(gcfg.td3, gcfg.model_based), T.td3_sample_fn(gcfg, env)

    def td3_fn(tc=tcfg, sample_fn=sample):
        return over_seeds(lambda td3, rep, k: td3_updates(
            tc, td3, T.td3_buffer(gcfg, rep), k, gcfg.td3_updates, sample_fn,
            sample_block=gcfg.td3.sample_block,
            seed_axis=A), 0, 0)

    if want("td3"):
        record("td3", td3_fn(), states.td3, states.replay, keys)
        for v in variants:
            ctx = contextlib.nullcontext()
            fn = None
            if v == "fixed_batch":
                fixed = jax.vmap(lambda rep, k: sample(k, rep, tcfg.batch_size))(states.replay, keys)

                def f(td3, fb, k):
                    return td3_updates(tcfg, td3, fb, k, gcfg.td3_updates,
                                       lambda kk, b, m: b if m == tcfg.batch_size else
                                       jax.tree_util.tree_map(
                                           lambda x: jnp.concatenate([x] * (m // tcfg.batch_size)),
                                           b),
                                       sample_block=gcfg.td3.sample_block, seed_axis=A)
                fn = over_seeds(f, 0, 0)
                args = (states.td3, fixed, keys)
            elif v == "bf16_compute":
                fn = td3_fn(dataclasses.replace(tcfg, compute_dtype="bfloat16"))
            elif v == "highest":
                ctx = jax.default_matmul_precision("highest")
            elif v == "half_batch":
                fn = td3_fn(dataclasses.replace(tcfg, batch_size=max(1, tcfg.batch_size // 2)))
            else:
                raise ValueError(f"unknown --td3-variants entry {v!r}; choose from {VARIANTS}")
            if fn is None:
                fn = td3_fn()
            if v != "fixed_batch":
                args = (states.td3, states.replay, keys)
            with ctx:
                record("td3_" + v, fn, *args)
    if gcfg.model_based and want("dynamics"):
        record("dynamics", over_seeds(lambda d, mr, k: learning.dynamics_updates(
            gcfg, d, mr, k, gcfg.dyn_updates), 0, 0), states.dyn, states.model_replay, keys)
    if want("step"):
        fn, st, active = SG.group_step_program(states, mesh)
        record("step", fn, st, active)
        out["env_steps_per_s"] = n * gcfg.steps_per_iteration_total / out["step_s"]
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="u_maze")
    p.add_argument("--algo", default="mf_dscpp")
    p.add_argument("--preset", default="fast")
    p.add_argument("--seeds-list", default="1,16", help="group sizes, comma separated")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--td3-variants", default="", help=f"comma separated, from {VARIANTS}")
    p.add_argument("--parts", default=",".join(DEFAULT_PARTS),
                   help=f"comma separated, from {','.join(PARTS)} (default: all but learn)")
    p.add_argument("--small", action="store_true", help="tiny sizes (CPU smoke test)")
    p.add_argument("--trace", action="store_true",
                   help="also run each part once under the JAX profiler and summarise its kernels")
    p.add_argument("--hlo-dir", default=None, help="write each part's optimised HLO here")
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)

    from dscpp_jax.runtime import use_fusion_autotuner_off
    use_fusion_autotuner_off()   # as `train` runs (before JAX touches a device)
    import jax

    from dscpp_jax.config import parse_value, preset
    sys.path.insert(0, os.path.join(ROOT, "experiments"))
    from bench_seeds import SMALL

    overrides = dict(SMALL) if a.small else {}
    for s in a.set:
        k, v = s.split("=", 1)
        overrides[k] = parse_value(k, v)
    cfg = preset(a.preset, a.env, a.algo, **overrides).validate()
    variants = [v for v in a.td3_variants.split(",") if v]
    for v in variants:
        if v not in VARIANTS:
            p.error(f"unknown --td3-variants entry {v!r}; choose from {', '.join(VARIANTS)}")
    parts = tuple(x for x in a.parts.split(",") if x)
    for x in parts:
        if x not in PARTS:
            p.error(f"unknown --parts entry {x!r}; choose from {', '.join(PARTS)}")
    dev = jax.devices()[0]
    print(f"{a.env} {a.algo} on {dev.device_kind} ({jax.default_backend()})", flush=True)
    rows = []
    for n in [int(x) for x in a.seeds_list.split(",")]:
        rows.append(profile(cfg, n, a.reps, variants, parts, a.trace, a.hlo_dir))
    import importlib.metadata as md

    def ver(name):
        try:
            return md.version(name)
        except md.PackageNotFoundError:
            return None
    rec = {"command": " ".join(["python", "experiments/profile_seed_group.py"] + list(argv or sys.argv[1:])),
           "device": dev.device_kind, "backend": jax.default_backend(),
           "versions": {k: ver(k) for k in ("jax", "jaxlib", "mujoco", "mujoco-mjx", "warp-lang")},
           "python": platform.python_version(), "env": a.env, "algo": a.algo,
           "overrides": {k: str(v) for k, v in overrides.items()}, "rows": rows}
    if a.out:
        os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
        with open(a.out, "w") as f:
            json.dump(rec, f, indent=1)
        print("wrote", a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
