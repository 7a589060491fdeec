"""Plain NumPy forward passes of the Flax MLPs, the oracle of the TD3 tests."""
import jax
import numpy as np


def to_np(tree):
    """A pytree of arrays as float64 NumPy arrays."""
    return jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64), tree)


def np_mlp(p, x, n_hidden):
    """The MLP of `networks.py` (ReLU hidden layers, linear output) on parameters `p`."""
    for i in range(n_hidden):
        x = np.maximum(x @ p[f"hidden_{i}"]["kernel"] + p[f"hidden_{i}"]["bias"], 0.0)
    return x @ p["out"]["kernel"] + p["out"]["bias"]
