"""MuJoCo Warp's kernel build from an empty kernel cache: one module after another at its first
launch, against the step's modules found by a dry run and compiled on several threads
(`envs.warp_kernels`, what `AntMazeEnv.build_warp_kernels` does by default).

Each setting runs in a fresh process with an empty Warp kernel cache of its own, so every module
is compiled (the first `--repeat` run of a setting is as cold as a new machine's; later ones
are in new empty caches too):

    python experiments/bench_warp_build.py --env u_maze --workers 1 0 --out bench_warp_build.json

`--workers 0` is one thread per CPU core. On a machine without a CUDA device the build runs on
Warp's CPU device; `--arch 90` instead compiles the step's modules (found by the dry run) for that
CUDA architecture with NVRTC, as a GPU host would, without a GPU (`warp.compile_aot_module`; the
compile only, not the load onto a device). Prints a table and writes JSON (`--out`).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

PREAMBLE = r"""
import json, sys, time
from concurrent.futures import ThreadPoolExecutor
sys.path.insert(0, {root!r})
import warp as wp
wp.config.kernel_cache_dir = {cache!r}
wp.config.quiet = True
wp.init()
from dscpp_jax import envs
from dscpp_jax.envs.warp_kernels import default_workers, modules_launched
from mujoco.mjx.third_party import mujoco_warp as mjwarp
env = envs.make({env!r}, physics="warp", warp_worlds=1)
workers = {workers} or default_workers()

def step_modules(device):
    # the modules the step loads, by a dry run (nothing compiles)
    with wp.ScopedDevice(device):
        m, d = env.warp_one_world()
        return list({{id(x[0]): x[0] for x in modules_launched(lambda: mjwarp.step(m, d))}}.values())
"""

# the build itself, on the machine's first CUDA device or else Warp's CPU device
CHILD = PREAMBLE + r"""
device = "cuda:0" if wp.is_cuda_available() else "cpu"
t = time.perf_counter()
env.build_warp_kernels(device, workers={workers})
build = time.perf_counter() - t
print(json.dumps({{"device": wp.get_device(device).name, "build_s": round(build, 3),
                  "modules": len(step_modules(device)), "workers": workers}}))
"""

# NVRTC's compile for a CUDA architecture only, on any machine
CHILD_ARCH = PREAMBLE + r"""
mods = step_modules("cpu")
def compile_one(mod):
    wp.compile_aot_module(mod, arch={arch}, module_dir={cache!r} + "/aot", use_ptx=False)
t = time.perf_counter()
if workers <= 1:
    for mod in mods:
        compile_one(mod)
else:
    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(compile_one, mods))
print(json.dumps({{"device": "NVRTC sm_{arch} (compile only)", "build_s": round(time.perf_counter() - t, 3),
                  "modules": len(mods), "workers": workers}}))
"""


def run_one(env: str, workers: int, arch: int = 0) -> dict:
    with tempfile.TemporaryDirectory(prefix="warp_cache_") as cache:
        code = (CHILD_ARCH.format(root=ROOT, cache=cache, env=env, workers=workers, arch=arch) if arch
                else CHILD.format(root=ROOT, cache=cache, env=env, workers=workers))
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
        if out.returncode != 0:
            raise SystemExit(f"error: the build with --workers {workers} failed:\n{out.stderr[-3000:]}")
        return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="u_maze")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 0],
                   help="settings to compare (1: one module at a time at its launch, as Warp "
                        "does by itself; 0: one thread per core)")
    p.add_argument("--repeat", type=int, default=1)
    p.add_argument("--arch", type=int, default=0,
                   help="compile for this CUDA architecture with NVRTC instead (e.g. 90 for H100/H200)")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if any(w < 0 for w in args.workers) or args.repeat < 1:
        p.error("--workers are >= 0 and --repeat >= 1")
    rows = []
    for r in range(args.repeat):
        for w in args.workers:
            row = run_one(args.env, w, args.arch)
            row.update(setting=w, repeat=r)
            rows.append(row)
            print(f"workers {row['workers']:>3} ({'serial' if w == 1 else 'dry run + pool'}): "
                  f"{row['build_s']:7.2f} s for {row['modules']} modules on {row['device']}",
                  flush=True)
    result = {"env": args.env, "arch": args.arch or None, "cpu_count": os.cpu_count(), "runs": rows}
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return result


if __name__ == "__main__":
    main()
