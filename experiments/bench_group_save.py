"""What a checkpoint holds the training loop for a seed group's state, the first save and the later
ones: orbax's asynchronous save (what `seed_group.GroupCheckpointer` does) against a plain
`jax.device_get` (the host copy a single run's `checkpoint.Checkpointer` makes), with the number
of XLA compilations during each.

    python experiments/bench_group_save.py --seeds 15 --out group15.json

The state is synthetic, with the layout that matters (two large buffers, a few hundred small
arrays, a leading seed axis), so it runs without the physics packages; `bench_checkpoint.py`
times the real training state.
"""
import argparse
import json
import shutil
import tempfile
import time

import jax
import jax.numpy as jnp
import orbax.checkpoint as ocp


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=15)
    ap.add_argument("--small", type=int, default=340, help="number of small arrays")
    ap.add_argument("--buffer-rows", type=int, default=1_000_000,
                    help="rows of the large replay-like buffer (the model buffer has 0.3 of them)")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    compiles = [0]   # XLA compile events while a save runs
    jax.monitoring.register_event_duration_secs_listener(
        lambda e, d, **k: compiles.__setitem__(0, compiles[0] + ("backend_compile" in e)))
    G = a.seeds
    shapes = [(G, a.buffer_rows, 20), (G, max(1, int(0.3 * a.buffer_rows)), 32)] + [
        (G, (i % 37) + 1, (i % 11) + 1) for i in range(a.small)]
    tree = {f"a{i:03d}": jnp.full(s, i, jnp.float32) for i, s in enumerate(shapes)}
    bump = jax.jit(lambda t: jax.tree_util.tree_map(lambda x: x + 1, t))
    tree = jax.block_until_ready(bump(tree))
    nbytes = sum(x.nbytes for x in tree.values())
    res = dict(device=str(jax.devices()[0].device_kind), seeds=G, arrays=len(tree),
               gbytes=round(nbytes / 1e9, 3), orbax=getattr(ocp, "__version__", "?"),
               jax=jax.__version__, orbax_async=[], device_get=[])
    d = tempfile.mkdtemp()
    m = ocp.CheckpointManager(d, options=ocp.CheckpointManagerOptions(max_to_keep=2, create=True))
    for step in range(a.rounds):
        tree = jax.block_until_ready(bump(tree))
        c0, t = compiles[0], time.perf_counter()
        m.save(step, args=ocp.args.StandardSave(tree), force=True)
        hold = time.perf_counter() - t
        m.wait_until_finished()
        r = dict(step=step, hold_s=round(hold, 3), total_s=round(time.perf_counter() - t, 3),
                 compiles=compiles[0] - c0)
        res["orbax_async"].append(r); print("orbax", r, flush=True)
    for step in range(a.rounds):
        tree = jax.block_until_ready(bump(tree))
        c0, t = compiles[0], time.perf_counter()
        h = jax.device_get(tree)
        r = dict(step=step, hold_s=round(time.perf_counter() - t, 3), compiles=compiles[0] - c0)
        del h
        res["device_get"].append(r); print("device_get", r, flush=True)
    m.close()
    shutil.rmtree(d, ignore_errors=True)
    if a.out:
        with open(a.out, "w") as f:
            json.dump(res, f, indent=1)
    return res


if __name__ == "__main__":
    main()
