"""Load a script of ``experiments/`` (not a package) as a module, for its smoke tests."""
from __future__ import annotations

import importlib.util
import os
import types

EXPERIMENTS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                           "experiments")


def load(name: str) -> types.ModuleType:
    """``experiments/<name>.py`` as a fresh module named ``name``."""
    spec = importlib.util.spec_from_file_location(name, os.path.join(EXPERIMENTS, f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
