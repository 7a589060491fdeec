"""How long a periodic checkpoint holds up the training loop: a plain save (write, read back,
prune before the loop goes on) against a background save (`save(..., wait=False)`: the loop goes on
once the state is in host memory; the rest finishes on a worker thread).

    python experiments/bench_checkpoint.py --env u_maze --algo mb_dscpp --seeds-list 1,10 --out bench_checkpoint.json

For each group size N it builds the training state (one run for N = 1, `dscpp_jax.init_group` for
N > 1) at the preset's sizes (replay buffers included, which dominate), then saves it `--repeat`
times each way into a temporary directory and reports the median seconds the caller was blocked,
and for the background save also the seconds until it had finished. Writes JSON (device,
versions, command, every number).

A state fresh from `init` is mostly zeros, which orbax's compressed files store almost for free;
a trained run's buffers are not. `--filled` first overwrites every floating-point array with
random numbers, which writes like (or worse than) a run whose buffers are full.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)


def _nbytes(tree) -> int:
    import jax
    return int(sum(getattr(x, "nbytes", 0) for x in jax.tree_util.tree_leaves(tree)))


def filled(tree, seed: int = 0):
    """`tree` with every non-empty floating-point array replaced by standard normal numbers (same
    shape, dtype and placement); integer, boolean and key arrays as they are."""
    import jax
    import jax.numpy as jnp
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    key, out = jax.random.key(seed), []
    for i, x in enumerate(leaves):
        if (hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating)
                and getattr(x, "size", 0) > 0):
            v = jax.random.normal(jax.random.fold_in(key, i), x.shape, jnp.float32).astype(x.dtype)
            x = jax.device_put(v, x.sharding)
        out.append(x)
    return jax.tree_util.tree_unflatten(treedef, out)


def bench_one(env: str, algo: str, n: int, repeat: int, workdir: str,
              fill: bool = False) -> dict:
    import jax

    from dscpp_jax import checkpoint as ck
    from dscpp_jax import config as C
    from dscpp_jax import seed_group as SG
    from dscpp_jax import trainer as T
    cfg = C.preset("fast", env, algo)
    if n == 1:
        state = T.init(jax.random.key(0), cfg)
        saver = ck.Checkpointer(os.path.join(workdir, f"n{n}"), keep=2)
    else:
        state = SG.init_group(list(range(n)), cfg)
        saver = SG.GroupCheckpointer(os.path.join(workdir, f"n{n}"), keep=2)
    if fill:
        state = filled(state)
    jax.block_until_ready(state)
    plain, blocked, finished = [], [], []
    step = 0
    try:
        for _ in range(repeat):
            step += 1
            t0 = time.perf_counter()
            saver.save(step, state)
            plain.append(time.perf_counter() - t0)
            step += 1
            t0 = time.perf_counter()
            saver.save(step, state, wait=False)
            blocked.append(time.perf_counter() - t0)
            saver.wait()
            finished.append(time.perf_counter() - t0)
    finally:
        saver.close()
    med = statistics.median
    return {"seeds": n, "state_mb": _nbytes(ck.as_stored(ck.to_storable(state))) / 1e6,
            "plain_blocked_s": med(plain), "background_blocked_s": med(blocked),
            "background_finished_s": med(finished), "filled": fill, "plain_all_s": plain,
            "background_blocked_all_s": blocked, "background_finished_all_s": finished}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env", default="u_maze")
    p.add_argument("--algo", default="mb_dscpp")
    p.add_argument("--seeds-list", default="1", help="group sizes, e.g. 1,10")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--dir", default=None, help="where to write the checkpoints (default: a "
                   "temporary directory, deleted afterwards)")
    p.add_argument("--filled", action="store_true", help="random numbers in every floating-point "
                   "array first (written like full buffers; default: the state as `init` makes it)")
    p.add_argument("--out", default=None, help="JSON file for the results")
    a = p.parse_args(argv)
    if a.repeat < 1:
        p.error("--repeat must be >= 1")
    try:
        sizes = [int(x) for x in a.seeds_list.split(",") if x.strip()]
    except ValueError:
        p.error(f"--seeds-list {a.seeds_list!r}: give group sizes such as 1,10")
    if not sizes or min(sizes) < 1:
        p.error("--seeds-list: every group size must be >= 1")
    import jax
    workdir = a.dir or tempfile.mkdtemp(prefix="bench_checkpoint_")
    rows = []
    try:
        for n in sizes:
            r = bench_one(a.env, a.algo, n, a.repeat, workdir, fill=a.filled)
            rows.append(r)
            print(f"{a.env}/{a.algo} N={n}: state {r['state_mb']:.0f} MB; loop blocked "
                  f"{r['plain_blocked_s']:.2f} s by a plain save, {r['background_blocked_s']:.2f} s "
                  f"by a background save (finished after {r['background_finished_s']:.2f} s)",
                  flush=True)
    finally:
        if a.dir is None:
            shutil.rmtree(workdir, ignore_errors=True)
    from importlib import metadata
    out = {"command": "python " + " ".join([os.path.relpath(__file__, ROOT)] + sys.argv[1:]),
           "device": str(jax.devices()[0].device_kind), "platform": jax.default_backend(),
           "cpu_count": os.cpu_count(), "python": platform.python_version(),
           "jax": jax.__version__, "orbax": metadata.version("orbax-checkpoint"),
           "env": a.env, "algo": a.algo, "repeat": a.repeat, "filled": a.filled, "results": rows}
    if a.out:
        with open(a.out, "w") as f:
            json.dump(out, f, indent=1)
        print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
