"""One place that initialises Taichi, so the arch and precision are chosen once, by the scene."""
from __future__ import annotations

import os

import taichi as ti

CACHE_LIMIT_BYTES = 1024**3  # Taichi takes a C int: under 2 GiB
"""Taichi's default offline cache (100 MiB, least recently used out) holds fewer kernels than the
test suite and reports compile: at that size a warm run recompiles what the cache evicted."""

_current: tuple[str, str] | None = None
generation = 0  # bumped on every re-initialisation; simulators built before it are dead


def init_taichi(arch: str = "cpu", dtype: str = "float32") -> None:
    """Initialise (or re-initialise, if arch/dtype changed) Taichi with the offline cache on.

    Re-initialising frees every field, so simulators from an earlier configuration stop
    working; `Simulator` checks `generation` and says so instead of crashing.
    """
    global _current, generation
    wanted = (arch, dtype)
    if _current == wanted:
        return
    if _current is not None:
        ti.reset()
    arch_obj = {"cpu": ti.cpu, "cuda": ti.cuda, "gpu": ti.gpu, "vulkan": ti.vulkan, "metal": ti.metal}[arch]
    cache_dir = os.environ.get("CODESIGN_TAICHI_CACHE")  # default: Taichi's own (~/.cache/taichi)
    ti.init(
        arch=arch_obj,
        default_fp=ti.f64 if dtype == "float64" else ti.f32,
        default_ip=ti.i32,
        offline_cache=True,
        offline_cache_max_size_of_files=CACHE_LIMIT_BYTES,
        **({"offline_cache_file_path": cache_dir} if cache_dir else {}),
        log_level=ti.WARN,
    )
    _current = wanted
    generation += 1


MAX_SCATTER_COPIES = 4
"""p2g on a CPU scatters each thread's chunk of particles into a private grid (2.5x to 4x faster
than float atomic adds, measured); each copy is a dense grid of 4 floats per node, so their
number is capped: more threads than copies leave the rest idle during p2g."""


def scatter_copies() -> int:
    """Private grids for p2g: one per CPU thread (up to MAX_SCATTER_COPIES); 1 on a GPU, whose
    atomic adds are native (1 means one shared grid with atomic adds). The environment variable
    CODESIGN_SCATTER_COPIES overrides it (benchmarks compare the two scatters with it)."""
    from taichi.lang import impl

    forced = os.environ.get("CODESIGN_SCATTER_COPIES")
    if forced:
        if not forced.isdigit() or int(forced) < 1:
            raise ValueError(f"CODESIGN_SCATTER_COPIES must be a positive integer, got {forced!r}")
        return int(forced)
    cfg = impl.current_cfg()
    if cfg.arch != ti.x64 and cfg.arch != ti.arm64:
        return 1
    return max(1, min(cfg.cpu_max_num_threads, MAX_SCATTER_COPIES))


def reset() -> None:
    """Free every field and compiled kernel of this process; the next simulator starts afresh.

    Taichi's offline cache keys kernels by, among others, the ids of the fields they touch,
    which count up in allocation order; starting from a fresh program makes those ids (and so
    cache hits) independent of whatever was simulated before in the process.
    """
    global _current, generation
    if _current is not None:
        ti.reset()
        _current = None
        generation += 1
