"""Dynamics-model gradient steps: drawing minibatches through the valid rows' positions (listed
once, one gather per draw; what `dynamics.dynamics_train` does) against a binary search of the
running count of valid rows in every step (what it did before 2026-11-29). Both draw the same
indices; the benchmark checks that, then times each at the ant preset's sizes.

    python experiments/bench_replay_draws.py --out bench_replay_draws.json       # ant U-maze sizes
    python experiments/bench_replay_draws.py --steps 8 --capacity 5000 --hidden 32 --batch 64  # CPU smoke

Prints and writes seconds per call of `--steps` model steps (median of `--reps`), the device and
the versions.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)


def searched_train(cfg, state, buffer, key, num_steps: int):
    """`dynamics_train` as it was: each step searches the running count for its draws."""
    import jax
    import jax.numpy as jnp

    from dscpp_jax.dynamics import _buffer_arrays, dynamics_update
    obs, act, nxt, mask = _buffer_arrays(buffer)
    E, B = cfg.ensemble_size, cfg.batch_size
    cdf = jnp.cumsum(mask.astype(jnp.int32))
    total = cdf[-1]

    def body(st, k):
        u = jax.random.randint(k, (E, B), 0, jnp.maximum(total, 1))
        idx = jnp.minimum(jnp.searchsorted(cdf, u, side="right"), obs.shape[0] - 1)
        new, m = dynamics_update(cfg, st, (obs[idx], act[idx], nxt[idx]), k)
        new = jax.tree.map(lambda a, c: jnp.where(total > 0, a, c), new, st)
        return new, m["loss"]

    return jax.lax.scan(body, state, jax.random.split(key, num_steps))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", type=int, default=640, help="model steps per call (ant preset: 640)")
    p.add_argument("--capacity", type=int, default=300_000, help="model replay rows")
    p.add_argument("--fill", type=float, default=0.5, help="share of the rows that are valid")
    p.add_argument("--obs-dim", type=int, default=29)
    p.add_argument("--act-dim", type=int, default=8)
    p.add_argument("--hidden", type=int, default=500)
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--reps", type=int, default=5)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if min(args.steps, args.capacity, args.hidden, args.batch, args.reps) < 1 or not 0 < args.fill <= 1:
        p.error("sizes must be >= 1 and 0 < --fill <= 1")

    import jax
    import jax.numpy as jnp
    import numpy as np

    from dscpp_jax.dynamics import (DynamicsConfig, dynamics_fit_normaliser, dynamics_init,
                                    dynamics_train)
    from dscpp_jax.run_logging import library_versions
    cfg = DynamicsConfig(ensemble_size=1, hidden=(args.hidden, args.hidden), lr=1e-3,
                         batch_size=args.batch)
    rng = np.random.default_rng(0)
    n = args.capacity
    obs = jnp.asarray(rng.normal(size=(n, args.obs_dim)), jnp.float32)
    act = jnp.asarray(rng.uniform(-1, 1, size=(n, args.act_dim)), jnp.float32)
    nxt = obs + 0.1 * jnp.asarray(rng.normal(size=(n, args.obs_dim)), jnp.float32)
    valid = jnp.asarray(np.arange(n) < int(args.fill * n))   # a ring filling up: a prefix
    buf = (obs, act, nxt, valid)
    state = dynamics_init(jax.random.PRNGKey(0), args.obs_dim, args.act_dim, cfg)
    state = dynamics_fit_normaliser(state, obs, act, nxt, valid, cfg=cfg)
    key = jax.random.PRNGKey(1)

    listed = jax.jit(lambda s, k: dynamics_train(cfg, s, buf, k, args.steps))
    searched = jax.jit(lambda s, k: searched_train(cfg, s, buf, k, args.steps))
    a, b = listed(state, key), searched(state, key)
    same = all(bool(jnp.array_equal(x, y)) for x, y in
               zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))
    out = {}
    for name, fn in (("positions_listed_once_s", listed), ("searched_per_step_s", searched)):
        ts = []
        for _ in range(args.reps):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(state, key))
            ts.append(time.perf_counter() - t0)
        out[name] = statistics.median(ts)
    d = jax.devices()[0]
    res = {"command": " ".join([os.path.basename(sys.executable)] + sys.argv),
           "device": getattr(d, "device_kind", d.platform), "python": platform.python_version(),
           "versions": library_versions(), "args": vars(args), "same_result": same, **out,
           "per_step_ms": {k[:-2]: 1e3 * v / args.steps for k, v in out.items()}}
    print(f"{args.steps} model steps on {res['device']}: positions listed once "
          f"{out['positions_listed_once_s']:.4f} s, searched in every step "
          f"{out['searched_per_step_s']:.4f} s; same result: {same}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(res, f, indent=2)
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
