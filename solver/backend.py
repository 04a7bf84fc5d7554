"""Taichi start-up: the one place that calls ti.init (never at import time)."""
from __future__ import annotations

import contextlib
import gc
import glob
import io
import logging
import os
import re
import subprocess
import sys

from .errors import SolverError

log = logging.getLogger("sphshot")
_current: tuple | None = None
_arch_name: str | None = None


class BackendUnavailable(SolverError):
    """The asked-for Taichi backend cannot start on this machine."""


def nvidia_present() -> bool:
    """An NVIDIA GPU's device node exists."""
    return bool(glob.glob("/dev/nvidia[0-9]*"))


def _render_node_present() -> bool:
    """A DRM render node exists (an AMD or Intel GPU's, or a VM's)."""
    return bool(glob.glob("/dev/dri/renderD*"))


def _runs_our_kernels() -> bool:
    """The device Taichi started on runs what the kernels need besides float32: float64 (the
    step's clock, clock.py) and int64 atomics (the surfacer's fixed-point sums). A Vulkan device
    without them (Intel's Xe GPUs have no float64) would fail at the first launch; this small
    kernel fails here instead."""
    import taichi as ti

    from .probe import k_probe

    try:
        f, k = ti.ndarray(ti.f64, 1), ti.ndarray(ti.i64, 1)
        k_probe(f, k)
        return bool(f.to_numpy()[0] == 1.5 and k.to_numpy()[0] == 6 << 33)
    except Exception:       # noqa: BLE001 - whatever the device's compiler or driver says
        return False


def vulkan_starts(software: bool = False) -> bool:
    """Taichi starts on a Vulkan device here; unless `software`, one that is not Mesa's software
    device (lavapipe). Asked in a child process: a failed start would leave this process's
    Taichi uninitialised, and the Vulkan loader reads which drivers to leave out once a process."""
    probe = ("import taichi as ti; ti.init(arch=ti.vulkan, offline_cache=False); "
             "import sys; sys.exit(0 if ti.lang.impl.current_cfg().arch == ti.vulkan else 1)")
    env = {**os.environ, "TI_LOG_LEVEL": "error"}
    if not software:
        env["VK_LOADER_DRIVERS_DISABLE"] = "*lvp*"
    try:
        return subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True,
                              timeout=120).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def allowed_cpus() -> list[int]:
    """The cores this process may run on: its CPU affinity (a SLURM allocation, a taskset, a
    Dask worker's share), or every core where the OS has no affinity call (macOS)."""
    try:
        return sorted(os.sched_getaffinity(0))
    except AttributeError:
        return list(range(os.cpu_count() or 1))


def current_arch() -> str:
    """The arch Taichi runs on now: "cpu" (x64 or arm64), "cuda", "vulkan", ..."""
    import taichi as ti
    arch = ti.lang.impl.current_cfg().arch
    return "cpu" if arch in (ti.x64, ti.arm64) else arch.name


# Taichi's runtime reports a failure as RuntimeError("[file.cpp:function@line] what"): a device
# out of memory, a GPU lost or reset, a driver's error, a host allocation refused.
_RUNTIME_ERROR = re.compile(r"^\[[\w.]+:[^\]]*@\d+\]\s*")


def device_failure(exc: BaseException) -> str | None:
    """What the device said, on one line, where `exc` is a failure of Taichi's runtime rather
    than of the algorithm (the solver's own errors are SolverErrors) or of the calling code;
    else None."""
    import taichi as ti

    if isinstance(exc, SolverError) or not isinstance(exc, RuntimeError):
        return None
    text = str(exc)
    if not (isinstance(exc, ti.lang.exception.TaichiRuntimeError) or _RUNTIME_ERROR.match(text)):
        return None
    what = " ".join(_RUNTIME_ERROR.sub("", text).split()) or type(exc).__name__
    return what if len(what) <= 300 else what[:300] + "..."


def init_taichi(backend: str = "auto", threads: int = 0) -> str:
    """Start Taichi on `backend` (auto: CUDA, then Vulkan, then CPU); returns the arch used.

    Re-initialises only when asked for another backend or thread count: arrays made before a
    re-initialisation become invalid, so callers create their solver after this call.
    """
    global _current, _arch_name
    os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")
    # Taichi's own log: nothing below critical. Its warnings are a developer's; its errors come
    # back as exceptions too, which the callers turn into one line (device_failure). Set
    # TI_LOG_LEVEL=error (or warn) to see them as Taichi prints them.
    os.environ.setdefault("TI_LOG_LEVEL", "critical")
    import taichi as ti

    want = (backend, threads)
    if _current == want:
        return _arch_name
    if _current is not None:
        # Free the old program's unreachable arrays while it still runs: an Ndarray collected
        # after ti.init deletes itself through the new program (Ndarray.__del__), where a new
        # array may sit at its address. Once in a full test run, a sim re-initialised for two
        # threads then failed a launch with "argument not found".
        gc.collect()
    order = {"auto": ["cuda", "vulkan", "cpu"], "cpu": ["cpu"], "cuda": ["cuda"], "vulkan": ["vulkan"]}[backend]
    if backend == "auto" and not nvidia_present() and not (_render_node_present() and vulkan_starts()):
        # no GPU, or a render node with no GPU's Vulkan driver behind it (a VM's, say): Mesa's
        # lavapipe is a Vulkan device too, but a software one, slower than Taichi's CPU path
        order = ["cpu"]
    # By default the cores this process may use: a Dask worker's share (workers.PinToShare), a
    # SLURM allocation, a taskset. A thread count in the job file wins.
    n_threads = threads or len(allowed_cpus())
    chosen, lacking = None, []
    for name in order:
        arch = {"cuda": ti.cuda, "vulkan": ti.vulkan, "cpu": ti.cpu}[name]
        with contextlib.redirect_stdout(io.StringIO()):
            # ti.init prints "Starting on arch=..."; its log level: TI_LOG_LEVEL, above
            ti.init(arch=arch, cpu_max_num_threads=n_threads, default_fp=ti.f32, default_ip=ti.i32,
                    random_seed=0, offline_cache=True)
        if current_arch() == name:
            if name != "vulkan" or _runs_our_kernels():
                chosen = name
                break
            lacking.append(name)
        ti.reset()
    if chosen is None:
        why = " (its device lacks float64 or int64 atomics)" if lacking else ""
        raise BackendUnavailable(f"sim.backend: {backend!r} is not available on this machine{why} "
                                 f"(expected one of {order}); use backend = \"auto\" or \"cpu\"")
    _current, _arch_name = want, chosen
    log.info("taichi backend: %s%s", chosen, f" ({n_threads} thread(s))" if chosen == "cpu" else "")
    return chosen
