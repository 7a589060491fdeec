"""A one-line Warp kernel for tests/test_warp_kernels.py (Warp kernels live at a module's top level)."""
import warp as wp


@wp.kernel
def add_one(a: wp.array(dtype=float)):
    a[wp.tid()] += 1.0
