"""runtime: the device checks of a run (the ant on a CPU, a GPU that JAX does not use)."""
import jax

from dscpp_jax import runtime
from dscpp_jax.config import preset


def test_an_ant_on_the_cpu_says_so_and_names_the_gpu_install_where_a_gpu_is_visible(monkeypatch):
    ant, twin = preset("fast", "u_maze", "mb_dscpp"), preset("fast", "point_u_maze", "mb_dscpp")
    monkeypatch.setattr(jax, "default_backend", lambda: "cpu")
    monkeypatch.setattr(runtime, "gpu_visible", lambda: None)
    lines = runtime.cpu_warnings(ant)
    assert len(lines) == 1 and "meant for a GPU" in lines[0] and "point_u_maze" in lines[0]
    monkeypatch.setattr(runtime, "gpu_visible", lambda: "nvidia-smi")
    lines = runtime.cpu_warnings(ant)
    assert len(lines) == 2
    assert "a GPU is visible (nvidia-smi) but JAX runs on the CPU" in lines[1]
    assert runtime.GPU_INSTALL in lines[1] and "[cuda]" in runtime.GPU_INSTALL
    assert runtime.cpu_warnings(twin) == []                 # point-mass twins belong on a CPU
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert runtime.cpu_warnings(ant) == []


def test_gpu_visible_without_nvidia_smi_or_a_gpu_backend(monkeypatch):
    def no_gpu(backend=None):
        raise RuntimeError("Unknown backend gpu")
    monkeypatch.setattr(jax, "devices", no_gpu)
    monkeypatch.setattr(runtime.shutil, "which", lambda name: None)
    assert runtime.gpu_visible() is None
