"""How precisely do the learners' float32 matrix products run under the XLA flags `train` uses?

On a GPU, XLA may run a float32 dot with TensorFloat-32 inputs (10-bit mantissa) or in full float32,
and which kernel it picks (cuBLAS or a Triton GEMM) depends on flags such as
`--xla_gpu_deterministic_ops`. This script runs the TD3 twin critic and a dynamics-model-sized MLP,
forward and backward, one seed and a vmapped group of five, and compares each with a float64
NumPy reference. Run it once per flag set, in a fresh process each (XLA reads its flags once):

    XLA_FLAGS=--xla_gpu_experimental_enable_fusion_autotuner=false python experiments/probe_matmul_precision.py --tag nodet
    XLA_FLAGS="--xla_gpu_experimental_enable_fusion_autotuner=false --xla_gpu_deterministic_ops=true" python experiments/probe_matmul_precision.py --tag det

It prints, per case, the largest error relative to the reference's largest magnitude (about 1e-7
in float32, about 1e-3 with TensorFloat-32 inputs) and which GEMM kernels the compiled program
calls: cuBLAS(Lt) custom calls, Triton fusions, and `dot` ops left to XLA's own emitters (in the
compiled HLO; on a CPU every product is one). `--out FILE` saves the same as JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys

import numpy as np

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402



def _load_networks():
    """dscpp_jax/networks.py alone (flax only): the probe needs no physics packages."""
    import importlib.util
    path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "dscpp_jax", "networks.py")
    spec = importlib.util.spec_from_file_location("dscpp_jax_networks", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


TwinCritic = _load_networks().TwinCritic


def _dense_layers(params):
    """[(kernel, bias)] of a QNetwork-like parameter tree, in layer order (float64)."""
    names = sorted((k for k in params if k.startswith("hidden_")), key=lambda k: int(k.split("_")[1]))
    return [(np.asarray(params[k]["kernel"], np.float64), np.asarray(params[k]["bias"], np.float64))
            for k in names + ["out"]]


def _mlp64(layers, x):
    for i, (w, b) in enumerate(layers):
        x = x @ w + b
        if i < len(layers) - 1:
            x = np.maximum(x, 0.0)
    return x


def _gemm_kernels(compiled_text: str) -> dict:
    """How often the compiled HLO calls each GEMM kind (cuBLAS custom calls, Triton GEMM fusions)
    and which dot algorithms / precisions it names."""
    out = {
        "cublas_gemm": len(re.findall(r'custom_call_target="__cublas\$gemm"', compiled_text)),
        "cublas_lt": len(re.findall(r'custom_call_target="__cublas\$lt\$matmul', compiled_text)),
        "triton_gemm": len(re.findall(r"__triton\w*", compiled_text)),
        "dot_ops": len(re.findall(r"\bdot\(", compiled_text)),
    }
    algos = sorted(set(re.findall(r"algorithm=([a-z0-9_]+)", compiled_text)))
    precisions = sorted(set(re.findall(r"operand_precision=\{([^}]*)\}", compiled_text)))
    tf32 = len(re.findall(r"tf32", compiled_text, flags=re.IGNORECASE))
    out.update(algorithms=algos, operand_precisions=precisions, tf32_mentions=tf32,
               triton_kinds=sorted(set(re.findall(r"__triton\w*", compiled_text))))
    return out


def _rel(a, ref):
    return float(np.max(np.abs(np.asarray(a, np.float64) - ref)) / max(np.max(np.abs(ref)), 1e-30))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tag", default="run")
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--obs-dim", type=int, default=29)
    ap.add_argument("--act-dim", type=int, default=8)
    ap.add_argument("--hidden", type=int, default=256)
    ap.add_argument("--group", type=int, default=5)
    ap.add_argument("--out", default="")
    args = ap.parse_args(argv)

    rng = np.random.default_rng(0)
    B, D, A, G = args.batch, args.obs_dim, args.act_dim, args.group
    obs = rng.normal(size=(G, B, D)).astype(np.float32)
    goal = rng.normal(size=(G, B, 2)).astype(np.float32) * 5
    act = rng.uniform(-1, 1, size=(G, B, A)).astype(np.float32)
    critic = TwinCritic(hidden=(args.hidden, args.hidden))
    keys = jax.random.split(jax.random.PRNGKey(0), G)
    params = jax.vmap(lambda k: critic.init(k, obs[0], goal[0], act[0]))(keys)

    def q1(p, o, g, a):
        return critic.apply(p, o, g, a)[0]

    def loss(p, o, g, a):
        return jnp.mean(q1(p, o, g, a) ** 2)

    results = {"tag": args.tag, "backend": jax.default_backend(),
               "device": str(jax.devices()[0].device_kind),
               "xla_flags": os.environ.get("XLA_FLAGS", ""),
               "matmul_precision": str(jax.config.jax_default_matmul_precision), "cases": {}}

    # float64 references: the first head of seed 0, and of every seed
    def ref_q(s):
        heads = jax.tree_util.tree_map(lambda x: np.asarray(x[s][0]), params["params"]["heads"])
        x = np.concatenate([obs[s], goal[s], act[s]], axis=-1).astype(np.float64)
        return _mlp64(_dense_layers(heads), x)[:, 0]

    p0 = jax.tree_util.tree_map(lambda x: x[0], params)
    one = jax.jit(q1)
    grp = jax.jit(jax.vmap(q1))
    cases = {
        "critic_forward_one_seed": (one, (p0, obs[0], goal[0], act[0]), ref_q(0)),
        "critic_forward_group": (grp, (params, obs, goal, act), np.stack([ref_q(s) for s in range(G)])),
    }
    for name, (fn, inputs, ref) in cases.items():
        y = fn(*inputs)
        text = fn.lower(*inputs).compile().as_text()
        results["cases"][name] = dict(rel_err=_rel(y, ref), **_gemm_kernels(text))

    # backward: the gradient against a float64 finite-free reference is the jit-vs-highest gap
    g = jax.jit(jax.grad(loss))
    with jax.default_matmul_precision("highest"):
        g_hi = jax.jit(jax.grad(loss))(p0, obs[0], goal[0], act[0])
    g_lo = g(p0, obs[0], goal[0], act[0])
    errs = jax.tree_util.tree_leaves(jax.tree_util.tree_map(
        lambda a, b: float(jnp.max(jnp.abs(a - b)) / jnp.maximum(jnp.max(jnp.abs(b)), 1e-30)), g_lo, g_hi))
    text = g.lower(p0, obs[0], goal[0], act[0]).compile().as_text()
    results["cases"]["critic_grad_vs_highest"] = dict(rel_err=max(errs), **_gemm_kernels(text))

    # a dynamics-model-sized product (500 wide), float32
    x = rng.normal(size=(256, 39)).astype(np.float32)
    w1 = (rng.normal(size=(39, 500)) / np.sqrt(39)).astype(np.float32)
    w2 = (rng.normal(size=(500, 500)) / np.sqrt(500)).astype(np.float32)
    f = jax.jit(lambda x, a, b: jnp.maximum(x @ a, 0) @ b)
    y = f(x, w1, w2)
    ref = np.maximum(x.astype(np.float64) @ w1, 0) @ w2
    results["cases"]["mlp500_forward"] = dict(rel_err=_rel(y, ref), **_gemm_kernels(f.lower(x, w1, w2).compile().as_text()))

    for name, r in results["cases"].items():
        print(f"[{args.tag}] {name:26s} rel_err {r['rel_err']:.2e}  cublas {r['cublas_gemm']} "
              f"cublasLt {r['cublas_lt']} triton {r['triton_gemm']} dots {r['dot_ops']} "
              f"algorithms {r['algorithms']} precisions {r['operand_precisions']} tf32 {r['tf32_mentions']}")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(results, fh, indent=1)


if __name__ == "__main__":
    main()
