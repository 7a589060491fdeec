"""Build the Warp modules a function launches, many at once.

Warp compiles a module at the first launch of one of its kernels, so a function that launches
dozens of modules for the first time (MuJoCo Warp's physics step: about 30 for the ant) compiles
them one after another. `modules_launched` runs the function once with every launch on the calling
thread turned into a no-op that only notes the module it would have loaded, and `load_modules`
then compiles and loads those modules on a pool of threads, as `warp.force_load` does. A real call
afterwards finds them loaded (and the next process finds them in Warp's kernel cache).

The dry run relies on `warp.launch` returning without launching when its module's `load` returns
nothing, and replaces `warp.capture_while` / `warp.capture_if` (whose conditions live on the device
and would never change) by one pass through the loop body and both branches, and
`warp.get_suggested_block_size` on a CUDA device (which needs the kernel loaded) by a note of the
kernel's module and a placeholder block size for the skipped launch. Nothing else is touched, and
only on the thread that runs the dry run; other threads load and launch as usual.
Whatever the dry run misses the real call still compiles, one module at a time.
"""
from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

_lock = threading.Lock()   # one dry run at a time (the patches are process wide)
_local = threading.local()

DRY_BLOCK_SIZE = (256, 1)
"""What `warp.get_suggested_block_size` answers on a CUDA device during a dry run (block size,
minimum grid size): only ever used to size a launch that is skipped."""


def _is_cuda(device) -> bool:
    import warp as wp
    return wp.get_device(device).is_cuda


def modules_launched(fn: Callable[[], Any]) -> list[tuple[Any, Any, Any]]:
    """Call `fn()` with this thread's Warp launches skipped; return the (module, device,
    block_dim) of each module a launch asked for, in first-asked order, without duplicates. The
    arrays `fn` would have written are left as they were."""
    import warp as wp

    module_cls = wp.Module
    with _lock:
        orig_load = module_cls.load
        orig_while, orig_if = wp.capture_while, wp.capture_if
        orig_suggested = wp.get_suggested_block_size
        seen: dict[tuple, tuple] = {}

        def load(self, device, block_dim=None, *args, **kwargs):
            if getattr(_local, "dry", False):
                seen.setdefault((id(self), str(device), block_dim), (self, device, block_dim))
                return None   # `warp.launch` returns without launching
            return orig_load(self, device, block_dim, *args, **kwargs)

        def capture_while(condition, while_body, stream=None, **kwargs):
            if getattr(_local, "dry", False):
                if callable(while_body):
                    while_body(**kwargs)
                return None
            return orig_while(condition, while_body, stream=stream, **kwargs)

        def capture_if(condition, on_true=None, on_false=None, stream=None, **kwargs):
            if getattr(_local, "dry", False):
                for branch in (on_true, on_false):
                    if callable(branch):
                        branch(**kwargs)
                return None
            return orig_if(condition, on_true=on_true, on_false=on_false, stream=stream, **kwargs)

        def get_suggested_block_size(kernel, device=None):
            if getattr(_local, "dry", False) and _is_cuda(device):
                kernel.module.load(wp.get_device(device))   # noted, as the real call loads it
                return DRY_BLOCK_SIZE
            return orig_suggested(kernel, device)

        module_cls.load = load
        wp.capture_while, wp.capture_if = capture_while, capture_if
        wp.get_suggested_block_size = get_suggested_block_size
        _local.dry = True
        try:
            fn()
        finally:
            _local.dry = False
            module_cls.load = orig_load
            wp.capture_while, wp.capture_if = orig_while, orig_if
            wp.get_suggested_block_size = orig_suggested
    return list(seen.values())


MAX_DEFAULT_WORKERS = 16
"""Most compiles at once by default: each NVRTC compile holds up to about a gigabyte of host
memory, and a many-GPU host may start one training process per GPU at the same time."""


def default_workers() -> int:
    """One compile per CPU core this process may use, at most `MAX_DEFAULT_WORKERS`."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:   # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_DEFAULT_WORKERS))


def load_modules(modules: list[tuple[Any, Any, Any]], workers: int = 0) -> int:
    """Compile (or read from Warp's kernel cache) and load each (module, device, block_dim) of
    `modules_launched` on `workers` threads (0: `default_workers()`; 1: one after another).
    Returns how many were loaded. The first failure is raised once all have finished."""
    workers = workers or default_workers()
    if workers <= 1 or len(modules) <= 1:
        for m, device, block_dim in modules:
            m.load(device, block_dim)
        return len(modules)
    with ThreadPoolExecutor(max_workers=min(workers, len(modules))) as pool:
        futures = [pool.submit(m.load, device, block_dim) for m, device, block_dim in modules]
    for f in futures:
        f.result()
    return len(modules)
