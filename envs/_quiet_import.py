"""Import MuJoCo MJX without the notice its optional Warp back end prints when `warp-lang` is
not installed.

`mujoco.mjx.warp` probes for Warp at import time and, when the module is missing, prints
``Failed to import warp: No module named 'warp'`` (and the same for ``mujoco_warp``) with
`print`, not through `logging` or `warnings`. The JAX back end that this project uses does not
need Warp, so the line only alarms. `import_quietly` captures stdout while the module imports and
passes every other line through; a Warp that is installed but fails to load (a driver error,
say) is still reported, and an installed Warp is imported as before.
"""
from __future__ import annotations

import contextlib
import importlib
import io
import re
import sys
from types import ModuleType

# exactly the probe's message for a missing `warp` package (nothing else is hidden)
WARP_PROBE = re.compile(r"^Failed to import (warp|mujoco_warp): No module named 'warp(\.[\w.]+)?'$")


def import_quietly(name: str = "mujoco.mjx") -> ModuleType:
    """`importlib.import_module(name)`, minus the missing-Warp probe lines on stdout."""
    if name in sys.modules:
        return sys.modules[name]
    buf = io.StringIO()
    try:
        with contextlib.redirect_stdout(buf):
            return importlib.import_module(name)
    finally:
        kept = [line for line in buf.getvalue().splitlines(keepends=True)
                if not WARP_PROBE.match(line.rstrip("\r\n"))]
        if kept:
            sys.stdout.write("".join(kept))
