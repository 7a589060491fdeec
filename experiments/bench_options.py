"""Benchmark: refitting the initiation classifiers of 16 options, JAX vs scikit-learn.

For each size (points per option) it builds DSC-like data for 16 options (random-walk
trajectories of 51 points toward each option's goal + failed start states around it), then times

* JAX: ``fit_initiation_batch`` on all 16 options in one call (vmapped on accelerators): two-class
  SVC, then the one-class pessimistic SVM on the positives the SVC calls positive, on padded
  slots of the skill chain's layout (100 trajectories x 51 points + 100 negatives = 5,200 slots per option);
* scikit-learn: the same pipeline (``SVC.fit``, ``predict`` on the positives, ``OneClassSVM.fit``)
  for the 16 options one after the other, pinned to one CPU core;

and the SVC alone both ways. Decision agreement is printed beside the times (200x200 grid per
option: optimistic sign agreement, pessimistic agreement where |f_sklearn| > 1% of its max, SVC
training predictions). It also times the DP value table refresh of the skill chain (16 options x
100 input states x 100 output states through a TD3 critic) when ``dscpp_jax.subgoals`` is present.

Run: ``python experiments/bench_options.py`` (``make bench-options``); writes
``experiments/results/bench_options.json`` (``--out`` to change).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from dscpp_jax import initiation as ini  # noqa: E402
from dscpp_jax import svm  # noqa: E402

TRAJ_LEN = 51
POS_SLOTS = 100 * TRAJ_LEN
NEG_SLOTS = 100
GAMMA = 0.5


def dsc_like(rng, n_traj, n_neg, goal, radius=4.0):
    """Positive trajectories (start + 50 states drifting to ``goal``) and failed start states."""
    trajs = []
    for _ in range(n_traj):
        r = radius * np.sqrt(rng.uniform())
        th = rng.uniform(0, 2 * np.pi)
        x = goal + r * np.array([np.cos(th), np.sin(th)])
        pts = [x.copy()]
        for _ in range(TRAJ_LEN - 1):
            d = goal - x
            d = d / max(np.linalg.norm(d), 1e-6)
            x = x + 0.08 * d + rng.normal(0, 0.06, 2)
            pts.append(x.copy())
        trajs.append(np.stack(pts))
    pos = np.concatenate(trajs).astype(np.float32)
    r = rng.uniform(2.5, 8.0, n_neg)
    th = rng.uniform(0, 2 * np.pi, n_neg)
    neg = (goal + np.stack([r * np.cos(th), r * np.sin(th)], -1)).astype(np.float32)
    return pos, neg


def make_options(n_points, n_options, seed):
    """Per option (pos, neg) with about ``n_points`` points (2% negatives)."""
    rng = np.random.default_rng(seed)
    n_neg = max(3, int(round(0.02 * n_points)))
    n_traj = max(1, (n_points - n_neg) // TRAJ_LEN)
    n_neg = n_points - n_traj * TRAJ_LEN
    out = []
    for _ in range(n_options):
        goal = rng.uniform(-10, 10, 2)
        out.append(dsc_like(rng, n_traj, min(n_neg, NEG_SLOTS), goal))
    return out


def pad(options):
    K = len(options)
    pos_xy = np.zeros((K, POS_SLOTS, 2), np.float32)
    pos_mask = np.zeros((K, POS_SLOTS), bool)
    neg_xy = np.zeros((K, NEG_SLOTS, 2), np.float32)
    neg_mask = np.zeros((K, NEG_SLOTS), bool)
    for k, (pos, neg) in enumerate(options):
        pos_xy[k, : len(pos)] = pos
        pos_mask[k, : len(pos)] = True
        neg_xy[k, : len(neg)] = neg
        neg_mask[k, : len(neg)] = True
    return pos_xy, pos_mask, neg_xy, neg_mask


def grid_for(pos, neg, n=200):
    X = np.concatenate([pos, neg])
    lo, hi = X.min(0) - 1.0, X.max(0) + 1.0
    g = np.stack(np.meshgrid(np.linspace(lo[0], hi[0], n), np.linspace(lo[1], hi[1], n)), -1)
    return g.reshape(-1, 2).astype(np.float32)


def sklearn_pipeline(pos, neg):
    from sklearn.svm import SVC, OneClassSVM

    X = np.concatenate([pos, neg])
    y = np.r_[np.ones(len(pos)), np.zeros(len(neg))]
    cw = "balanced" if len(neg) >= 10 else None
    svc = SVC(kernel="rbf", gamma=GAMMA, C=1.0, class_weight=cw).fit(X, y)
    keep = pos[svc.predict(pos) == 1]
    occ = OneClassSVM(kernel="rbf", gamma=GAMMA, nu=0.1).fit(keep) if len(keep) else None
    return svc, occ


def sklearn_svc(pos, neg):
    from sklearn.svm import SVC

    X = np.concatenate([pos, neg])
    y = np.r_[np.ones(len(pos)), np.zeros(len(neg))]
    cw = "balanced" if len(neg) >= 10 else None
    return SVC(kernel="rbf", gamma=GAMMA, C=1.0, class_weight=cw).fit(X, y)


def time_sklearn(fn, options, reps):
    """Seconds to run ``fn`` over all options sequentially, pinned to one core (best of reps)."""
    old = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    if old:
        os.sched_setaffinity(0, {min(old)})
    try:
        times, models = [], None
        for _ in range(reps):
            t0 = time.perf_counter()
            models = [fn(p, n) for p, n in options]
            times.append(time.perf_counter() - t0)
    finally:
        if old:
            os.sched_setaffinity(0, old)
    return times, models


def time_jax(fn, args, reps):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return times, compile_s, out


def agreement(options, clfs, svc_models, sk_pipe, cache):
    """Per-option decision agreement between JAX and scikit-learn (sklearn grid values cached)."""
    rows = []
    for k, (pos, neg) in enumerate(options):
        g = grid_for(pos, neg)
        ck = jax.tree.map(lambda x: x[k], clfs)
        sk_svc, sk_occ = sk_pipe[k]
        if k not in cache:
            cache[k] = (sk_svc.decision_function(g), None if sk_occ is None else sk_occ.decision_function(g))
        f_sk, fo = cache[k]
        opt_j = np.asarray(ini.optimistic_contains(ck, g))
        row = {"optimistic_grid": float(np.mean(opt_j == (f_sk >= 0)))}
        X = np.concatenate([pos, neg])
        row["svc_train"] = float(np.mean(np.asarray(svm.predict(ck.optimistic, X)) == (sk_svc.predict(X) == 1)))
        row["max_abs_df_svc"] = float(np.max(np.abs(np.asarray(svm.decision_function(ck.optimistic, g)) - f_sk)))
        if sk_occ is not None:
            big = np.abs(fo) > 1e-2 * np.abs(fo).max()
            pes_j = np.asarray(ini.pessimistic_contains(ck, g))
            row["pessimistic_grid_masked"] = float(np.mean((pes_j == (fo > 0))[big]))
            row["pessimistic_grid"] = float(np.mean(pes_j == (fo > 0)))
            row["rho_rel_err_pessimistic"] = float(abs(float(ck.pessimistic.rho) - sk_occ.offset_[0]) / abs(sk_occ.offset_[0]))
        row["iters_jax"] = [int(ck.optimistic.n_iter), int(ck.pessimistic.n_iter)]
        row["iters_sklearn"] = [int(np.sum(sk_svc.n_iter_)), int(np.sum(sk_occ.n_iter_)) if sk_occ is not None else 0]
        if svc_models is not None:
            mk = jax.tree.map(lambda x: x[k], svc_models)
            row["svc_only_grid"] = float(np.mean((np.asarray(svm.decision_function(mk, g)) >= 0) == (f_sk >= 0)))
        rows.append(row)
    return rows


def summarize(rows):
    out = {}
    for key in rows[0]:
        vals = [r[key] for r in rows if key in r]
        if isinstance(vals[0], list):
            continue
        out[key] = {"min": min(vals), "mean": float(np.mean(vals)), "max": max(vals)}
    return out


def bench_dp(n_options, n_states, reps):
    """DP value table refresh time (skill chain of ``n_options`` rows, ``n_states`` inputs each)."""
    try:
        from dscpp_jax import options as opts
        from dscpp_jax import subgoals
        from dscpp_jax import td3
    except Exception as e:  # pragma: no cover - reported, not fatal
        return {"error": f"import failed: {e!r}"}
    if not hasattr(subgoals, "dp_value_table"):
        return {"error": "dscpp_jax.subgoals has no dp_value_table"}
    try:
        obs_dim, action_dim = 29, 8
        cfg = opts.ChainConfig(max_options=n_options, max_pos_traj=n_states, obs_dim=obs_dim, max_neg=10)
        chain = opts.chain_init(cfg, jnp.zeros(2))
        rng = np.random.default_rng(0)
        K, P, L = n_options, n_states, cfg.traj_len
        status = np.full((K,), opts.MATURE, np.int32)
        status[opts.GLOBAL] = opts.ALWAYS
        parent = np.arange(K, dtype=np.int32) - 1
        parent[: opts.GOAL + 1] = -1
        pos_xy = rng.uniform(-10, 10, (K, P, L, 2)).astype(np.float32)
        pos_obs = rng.normal(size=(K, P, obs_dim)).astype(np.float32)
        pos_obs[..., :2] = pos_xy[:, :, 0]
        chain = chain.replace(
            status=jnp.asarray(status), parent=jnp.asarray(parent), pos_xy=jnp.asarray(pos_xy),
            pos_mask=jnp.ones((K, P, L), bool), pos_obs=jnp.asarray(pos_obs),
            pess_ok=jnp.ones((K, P, L), bool), fitted=jnp.ones((K,), bool),
            num_options=jnp.asarray(K, jnp.int32))
        tcfg = td3.TD3Config()
        state = td3.td3_init(jax.random.key(0), obs_dim, 2, action_dim, tcfg)

        @jax.jit
        def refresh(chain, state):
            return subgoals.dp_value_table(chain, lambda o, g: td3.td3_value(tcfg, state, o, g))

        times, compile_s, table = time_jax(refresh, (chain, state), reps)
        return {"options": K, "states": P, "pairs": K * P * P, "critic_hidden": list(tcfg.hidden),
                "obs_dim": obs_dim, "compile_s": compile_s, "times_s": times,
                "median_ms": 1e3 * statistics.median(times), "min_ms": 1e3 * min(times),
                "finite": bool(np.isfinite(np.asarray(table.w)).all())}
    except Exception as e:  # pragma: no cover
        return {"error": f"{type(e).__name__}: {e}"}


def parse_solver(spec: str) -> svm.Solver:
    """'default', xla:STEPS:ARGMAX (or STEPS:ARGMAX) or pallas:CHUNK:WARPS:ARGMAX[:STEPS[:RESIDENT]]."""
    if spec == "default":
        return svm.resolve_inner(None)
    parts = spec.split(":")
    if parts[0] == "pallas" and 4 <= len(parts) <= 6:
        sv = svm.Solver(backend="pallas", chunk=int(parts[1]), warps=int(parts[2]), variadic=parts[3] == "v",
                        steps=svm.resolve_inner(None).steps)
        if len(parts) > 4:
            sv = sv._replace(steps=int(parts[4]))
        if len(parts) > 5:
            sv = sv._replace(resident=int(parts[5]))
        return svm.resolve_inner(sv)
    if parts[0] == "xla":
        parts = parts[1:]
    if len(parts) != 2:
        raise ValueError(f"bad --solver spec {spec!r}")
    return svm.resolve_inner(svm.Solver(steps=int(parts[0]), variadic=parts[1] == "v", backend="xla"))


def solver_name(sv: svm.Solver) -> str:
    argmax = "variadic" if sv.variadic else "two-pass"
    if sv.backend == "pallas":
        return (f"pallas,chunk={sv.chunk},warps={sv.warps},resident={sv.resident},steps={sv.steps},"
                f"{argmax}-argmax")
    return f"xla,steps={sv.steps},{argmax}-argmax"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 5000], help="points per option")
    ap.add_argument("--options", type=int, default=16)
    ap.add_argument("--reps", type=int, default=10, help="timed JAX repetitions (after a warm-up)")
    ap.add_argument("--sk-reps", type=int, default=3, help="timed scikit-learn repetitions")
    ap.add_argument("--solver", nargs="+", default=["default"],
                    help="SMO settings to compare: 'default' (the platform's), xla:STEPS:ARGMAX (XLA loop, "
                         "e.g. xla:8:v = 8 steps per convergence check, variadic argmax; t = two-pass "
                         "argmax; STEPS:ARGMAX alone means the same) or pallas:CHUNK:WARPS:ARGMAX[:STEPS[:RESIDENT]] "
                         "(the fused kernel, e.g. pallas:1024:4:v:8:1024; RESIDENT 0 = never in registers)")
    ap.add_argument("--dp-states", type=int, default=100)
    ap.add_argument("--no-dp", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results",
                                                  "bench_options.json"))
    args = ap.parse_args(argv)

    import sklearn

    dev = jax.devices()[0]
    meta = {
        "command": "python " + " ".join([os.path.relpath(sys.argv[0])] + sys.argv[1:]),
        "device": f"{dev.platform}: {getattr(dev, 'device_kind', str(dev))}",
        "jax_backend": jax.default_backend(),
        "versions": {"python": platform.python_version(), "jax": jax.__version__,
                     "jaxlib": getattr(jax.lib, "__version__", None) or __import__("jaxlib").__version__,
                     "numpy": np.__version__, "scikit-learn": sklearn.__version__},
        "cpu": platform.processor() or platform.machine(),
        "sklearn_threads": "main thread pinned to one core (libsvm is single-threaded)",
        "slots_per_option": POS_SLOTS + NEG_SLOTS,
        "batch_mode": ini.BATCH_MODE.get(jax.default_backend(), ini.BATCH_MODE["default"]),
        "default_solver": svm.resolve_inner(None)._asdict(),
        "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    try:
        with open("/proc/cpuinfo") as f:
            meta["cpu"] = next(l.split(":", 1)[1].strip() for l in f if l.startswith("model name"))
    except Exception:
        pass
    print(f"device {meta['device']}  jax {jax.__version__}  sklearn {sklearn.__version__}  cpu {meta['cpu']}")

    solvers = [parse_solver(spec) for spec in args.solver]
    solvers = list(dict.fromkeys(solvers))
    cfg = ini.InitiationConfig()
    pipes = {sv: jax.jit(lambda a, b, c, d, sv=sv: ini.fit_initiation_batch(a, b, c, d, cfg, solver=sv))
             for sv in solvers}
    svc_fn = jax.jit(jax.vmap(lambda x, l, m, b: svm.fit_svc(x, l, m, gamma=GAMMA, C=1.0, class_weight=b,
                                                              solver=solvers[0])))
    results = []
    out = {"meta": meta, "refit": results, "dp_table": None}

    def save():
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(out, f, indent=1)

    for size in args.sizes:
        options = make_options(size, args.options, args.seed + size)
        batch = pad(options)
        n_pts = [len(p) + len(n) for p, n in options]
        sk_pipe_t, sk_pipe = time_sklearn(sklearn_pipeline, options, args.sk_reps)
        sk_svc_t, _ = time_sklearn(sklearn_svc, options, args.sk_reps)
        res = {"points_per_option": int(np.mean(n_pts)), "negatives_per_option": len(options[0][1]),
               "options": args.options,
               "sklearn_pipeline_s": sk_pipe_t, "sklearn_svc_s": sk_svc_t, "jax": {}}
        results.append(res)
        jargs = tuple(jnp.asarray(a) for a in batch)
        labels = jnp.concatenate([jnp.ones(batch[1].shape, jnp.int32), jnp.zeros(batch[3].shape, jnp.int32)], 1)
        X = jnp.concatenate([jargs[0], jargs[2]], 1)
        M = jnp.concatenate([jargs[1], jargs[3]], 1)
        bal = jnp.sum(jargs[3], 1) >= 10
        sk_cache = {}
        best = None
        for n_sv, sv in enumerate(solvers):
            name = solver_name(sv)
            pt, pc, clfs = time_jax(pipes[sv], jargs, args.reps)
            svcs = None
            entry = {"solver": sv._asdict(), "pipeline_s": pt, "pipeline_compile_s": pc,
                     "pipeline_median_ms": 1e3 * statistics.median(pt),
                     "speedup_pipeline": min(sk_pipe_t) / statistics.median(pt)}
            if n_sv == 0:
                st, sc, svcs = time_jax(svc_fn, (X, labels, M, bal), args.reps)
                entry.update({"svc_s": st, "svc_compile_s": sc, "svc_median_ms": 1e3 * statistics.median(st),
                              "speedup_svc": min(sk_svc_t) / statistics.median(st)})
            rows = agreement(options, clfs, svcs, sk_pipe, sk_cache)
            entry.update({
                "converged_all": bool(np.all(np.asarray(clfs.optimistic.converged))
                                      & np.all(np.asarray(clfs.pessimistic.converged))),
                "max_iters": [int(np.max(np.asarray(clfs.optimistic.n_iter))),
                              int(np.max(np.asarray(clfs.pessimistic.n_iter)))],
                "agreement": summarize(rows), "per_option": rows})
            res["jax"][name] = entry
            if best is None or entry["pipeline_median_ms"] < res["jax"][best]["pipeline_median_ms"]:
                best = name
            res["best"] = best
            save()
            a = entry["agreement"]
            svc_txt = (f" | svc: sklearn {1e3 * min(sk_svc_t):8.1f} ms  jax {entry['svc_median_ms']:7.1f} ms"
                       f"  x{entry['speedup_svc']:5.1f}") if "svc_median_ms" in entry else ""
            print(f"n={res['points_per_option']:5d} {name} | pipeline: sklearn {args.options}x seq {1e3 * min(sk_pipe_t):8.1f} ms"
                  f"  jax {entry['pipeline_median_ms']:7.1f} ms  x{entry['speedup_pipeline']:5.1f}{svc_txt}"
                  f" | agree opt {a['optimistic_grid']['min']:.5f}"
                  f" pes(masked) {a.get('pessimistic_grid_masked', {}).get('min', float('nan')):.5f}"
                  f" train {a['svc_train']['min']:.5f} | iters {entry['max_iters']} conv {entry['converged_all']}"
                  f" | compile {pc:.1f}s", flush=True)

    dp = None if args.no_dp else bench_dp(args.options, args.dp_states, args.reps)
    out["dp_table"] = dp
    save()
    if dp is not None:
        if "error" in dp:
            print("DP table:", dp["error"])
        else:
            print(f"DP table refresh {dp['options']} options x {dp['states']} states ({dp['pairs']} critic "
                  f"pairs): median {dp['median_ms']:.2f} ms (compile {dp['compile_s']:.1f}s)")

    print()
    print("| points/option | sklearn, options fitted one after another (1 core) | JAX, all options in one call | speedup | optimistic grid agreement (min) | pessimistic masked agreement (min) |")
    print("|---:|---:|---:|---:|---:|---:|")
    for r in results:
        e = r["jax"][r["best"]]
        a = e["agreement"]
        print(f"| {r['points_per_option']} | {1e3 * min(r['sklearn_pipeline_s']):.1f} ms | {e['pipeline_median_ms']:.1f} ms"
              f" ({r['best']}) | {e['speedup_pipeline']:.1f}x | {a['optimistic_grid']['min']:.5f} |"
              f" {a.get('pessimistic_grid_masked', {}).get('min', float('nan')):.5f} |")
    if dp and "error" not in dp:
        print(f"\nDP table refresh ({dp['options']} options x {dp['states']} states): {dp['median_ms']:.2f} ms")

    print("wrote", args.out)


if __name__ == "__main__":
    main()
