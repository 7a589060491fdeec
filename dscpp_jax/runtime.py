"""The process JAX runs in: XLA flags, the persistent compilation cache and the device checks of
a run. Everything here is host-side and callable from the Python API (no argparse); the XLA
settings only take effect before JAX first touches a device.

    use_fusion_autotuner_off()      XLA's fusion autotuner off (slow compiles under a seed group)
    use_deterministic_ops(on)       deterministic GPU kernels (repeatable MJX runs on a GPU)
    use_xla_flags(deterministic)    both, as the command line sets them
    use_compile_cache(path)         JAX's persistent compilation cache
    device_warnings(cfg)            the lines a run prints about its physics and devices
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from typing import List, Optional

import jax

from dscpp_jax.config import Config

DETERMINISTIC_FLAG = "--xla_gpu_deterministic_ops=true"
FUSION_AUTOTUNER_FLAG = "--xla_gpu_experimental_enable_fusion_autotuner=false"
COMPILE_CACHE_ENV = "DSCPP_JAX_COMPILE_CACHE"
DEFAULT_COMPILE_CACHE = os.path.join("~", ".cache", "dscpp_jax", "xla")
GPU_INSTALL = "pip install -e '.[cuda]' (or: make install GPU=1)"
"""The install command that gives JAX its CUDA back end (the `cuda` extra of pyproject.toml)."""


def backends_initialized() -> bool:
    """Whether JAX already uses a device in this process (then XLA_FLAGS no longer matter)."""
    try:   # a private helper of JAX's; where a version lacks it, assume no device is in use yet
        from jax._src.xla_bridge import backends_are_initialized
    except ImportError:
        return False
    return backends_are_initialized()


def use_deterministic_ops(on: bool) -> bool:
    """Ask XLA for deterministic GPU kernels (``XLA_FLAGS`` += ``--xla_gpu_deterministic_ops``).

    Without it, XLA's GPU scatter-adds (MuJoCo MJX's contact assembly among them) use atomics,
    and two GPU runs of one seed drift apart from the first iteration; with it MJX runs repeat bit
    for bit, at a higher time per iteration on the ant (experiments/results/gpu_determinism).
    MuJoCo Warp's own kernels use atomics that this flag does not reach, so Warp runs do not
    repeat on a GPU either way. CPU runs repeat either way. XLA reads the flag when JAX first
    touches a device, so this only works before that; returns whether the flag is in effect for
    this process.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if not on or "xla_gpu_deterministic_ops" in flags:
        return "xla_gpu_deterministic_ops=true" in flags
    if backends_initialized():
        if jax.default_backend() != "gpu":
            return False   # CPU kernels repeat anyway
        print("warning: JAX already uses a device in this process; --deterministic cannot take "
              "effect (set XLA_FLAGS=--xla_gpu_deterministic_ops=true before starting Python)",
              file=sys.stderr)
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {DETERMINISTIC_FLAG}".strip()
    return True


def use_fusion_autotuner_off() -> bool:
    """Turn XLA's fusion autotuner off (``XLA_FLAGS`` +=
    ``--xla_gpu_experimental_enable_fusion_autotuner=false``) unless ``XLA_FLAGS`` already sets
    it either way.

    That autotuner compiles each large reduction and transpose fusion a second time with Triton's
    block-level emitter and times both. Under a seed group's vmap some of those fusions become
    large enough that the Triton variants take minutes to compile, for a few per cent faster
    iterations (docs/reproducibility.md, "XLA settings"). GEMM autotuning stays on. Like every
    XLA flag it only takes effect before JAX first touches a device; returns whether the
    autotuner is off for this process.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_gpu_experimental_enable_fusion_autotuner" in flags:
        return FUSION_AUTOTUNER_FLAG.lstrip("-") in flags
    if backends_initialized():
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {FUSION_AUTOTUNER_FLAG}".strip()
    return True


def use_xla_flags(deterministic: bool) -> bool:
    """The XLA flags of a run, set before JAX touches a device: the fusion autotuner off
    (`use_fusion_autotuner_off`) and deterministic kernels where asked (`use_deterministic_ops`,
    whose result this returns)."""
    use_fusion_autotuner_off()
    return use_deterministic_ops(deterministic)


def use_compile_cache(path: Optional[str], min_compile_time_s: float = 1.0) -> Optional[str]:
    """Keep compiled programs in directory ``path`` (JAX's persistent compilation cache), so that
    a resumed run, or an evaluation of a config trained before, loads its programs instead of
    compiling them again (the ant's ``train_step`` takes tens of seconds to compile).

    ``None`` picks ``$DSCPP_JAX_COMPILE_CACHE``, then JAX's own ``jax_compilation_cache_dir``
    setting, then ``~/.cache/dscpp_jax/xla``; ``"off"`` (or ``""``) uses no cache. Programs that
    compile faster than ``min_compile_time_s`` are not stored. JAX decides whether to use the
    cache at its first compilation, so this only takes effect before that. Returns the directory
    in use, or None.
    """
    if path is None:
        path = os.environ.get(COMPILE_CACHE_ENV)
    if path is None:
        path = jax.config.jax_compilation_cache_dir or DEFAULT_COMPILE_CACHE
    if not path or path.lower() == "off":
        return None
    path = os.path.abspath(os.path.expanduser(path))
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as e:
        print(f"warning: cannot use {path} as the compilation cache ({e}); compiling without it",
              file=sys.stderr)
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    return path


def is_ant(cfg: Config) -> bool:
    """Whether the run's environment is a MuJoCo ant maze (not a point-mass twin)."""
    return not cfg.env.startswith("point_")


def gpu_visible() -> Optional[str]:
    """How an NVIDIA GPU shows itself to this process although JAX has no GPU back end
    ("nvidia-smi", or "jax.devices" where JAX lists one but runs elsewhere), or None when none
    is visible."""
    try:
        if jax.devices("gpu"):
            return "jax.devices"
    except RuntimeError:   # no GPU back end in this JAX
        pass
    if shutil.which("nvidia-smi") is None:
        return None
    try:
        out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return "nvidia-smi" if out.returncode == 0 and "GPU" in out.stdout else None


def physics_line(cfg: Config) -> str:
    """The line an ant run prints about its physics back end and JAX's platform."""
    return (f"{cfg.env}: {'MuJoCo Warp' if cfg.task.physics == 'warp' else 'MJX (JAX)'} physics on "
            f"{jax.default_backend().upper()}")


def cpu_warnings(cfg: Config) -> List[str]:
    """The warnings for an ant run that JAX runs on the CPU: it is slow there, and where a GPU is
    visible (nvidia-smi, jax.devices) JAX is missing its CUDA back end, with the install command
    that fixes it. [] for point-mass twins and runs on an accelerator."""
    if not is_ant(cfg) or jax.default_backend() != "cpu":
        return []
    out = [f"WARNING: {cfg.env} is an MJX ant environment meant for a GPU; on a CPU it is very "
           f"slow. Use a point-mass twin (e.g. point_{cfg.env}) for CPU runs."]
    seen = gpu_visible()
    if seen is not None:
        out.append(f"WARNING: a GPU is visible ({seen}) but JAX runs on the CPU: this JAX has no "
                   f"CUDA back end (or JAX_PLATFORMS excludes it). Install it with: "
                   f"{GPU_INSTALL}")
    return out
