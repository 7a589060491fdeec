"""experiments/probe_matmul_precision.py: its float64 references match the networks on a CPU."""
import json

from experiment_scripts import load


def test_probe_references_match_float32_products_on_cpu(tmp_path):
    probe = load("probe_matmul_precision")
    out = tmp_path / "cpu.json"
    probe.main(["--tag", "cpu", "--batch", "16", "--hidden", "32", "--group", "2", "--out", str(out)])
    r = json.loads(out.read_text())
    assert r["backend"] == "cpu"
    cases = r["cases"]
    assert set(cases) == {"critic_forward_one_seed", "critic_forward_group", "critic_grad_vs_highest",
                          "mlp500_forward"}
    # a CPU runs float32 products in float32: far below TensorFloat-32's ~1e-3, and a wrong layer
    # order or a missing ReLU in the reference would be off by order one
    for name in ("critic_forward_one_seed", "critic_forward_group", "mlp500_forward"):
        assert cases[name]["rel_err"] < 1e-5, (name, cases[name]["rel_err"])
    assert cases["critic_grad_vs_highest"]["rel_err"] < 1e-5
    assert cases["critic_forward_one_seed"]["dot_ops"] >= 3
