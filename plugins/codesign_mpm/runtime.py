"""One place that initialises Taichi, so the arch and precision are chosen once, by the scene."""
from __future__ import annotations

import contextlib
import functools
import os
import sys
import weakref

import numpy as np
import taichi as ti
from taichi._snode.snode_tree import SNodeTree
from taichi.lang import impl

CACHE_LIMIT_BYTES = 1024**3  # Taichi takes a C int: under 2 GiB
"""Taichi's default offline cache (100 MiB, least recently used out) holds fewer kernels than the
test suite and reports compile: at that size a warm run recompiles what the cache evicted."""

POSITION_CACHE_LIMIT = 200_000
"""Source excerpts kept by `_memoize_source_positions` before the cache starts afresh."""

_current: tuple[str, str] | None = None
generation = 0  # bumped on every re-initialisation; simulators built before it are dead
_ndarrays: "weakref.WeakSet[ti.Ndarray]" = weakref.WeakSet()  # this program's live ndarrays
_outlived: list = []  # ndarrays of ended programs, never to be collected (see `ndarray`)
_trees: "weakref.WeakSet[SNodeTree]" = weakref.WeakSet()  # this program's live SNode trees (see `fields_tree`)


def ndarray(dtype, shape: tuple[int, ...]) -> "ti.Ndarray":
    """A Taichi ndarray that is safe to outlive its program.

    Collecting a Taichi ndarray asks the *current* program to free it by its address; after a
    reset that address can belong to a live ndarray of the new program, which is then freed
    under its owner (Taichi 1.7: memory reused behind a simulator's back, or a segmentation
    fault). So the ndarrays still alive when a program ends are kept from collection; their
    memory went with their program."""
    array = ti.ndarray(dtype, shape)
    _ndarrays.add(array)
    return array


def fields_tree(builder: ti.FieldsBuilder) -> SNodeTree:
    """`builder.finalize()`, the tree let go of its program when the program ends.

    Taichi's SNode tree holds its program, so a tree that outlives `ti.reset()` keeps the ended
    program alive until the tree is collected; the program's teardown then runs inside the next
    program and frees memory that program's ndarrays hold (Taichi 1.7: a segmentation fault in a
    later kernel)."""
    tree = builder.finalize()
    _trees.add(tree)
    return tree


def _end_program() -> None:
    """`ti.reset()`, the program torn down now: its surviving ndarrays are never collected and its
    surviving SNode trees let go of it (their `destroy()` is then a no-op)."""
    _outlived.extend(_ndarrays)
    _ndarrays.clear()
    for tree in _trees:
        tree.prog = None
    _trees.clear()
    ti.reset()


def init_taichi(arch: str = "cpu", dtype: str = "float32") -> None:
    """Initialise (or re-initialise, if arch/dtype changed) Taichi with the offline cache on.

    Re-initialising frees every field, so simulators from an earlier configuration stop
    working; `Simulator` checks `generation` and says so instead of crashing.
    """
    global _current, generation
    wanted = (arch, dtype)
    if _current == wanted:
        return
    _memoize_source_positions()
    _memoize_kernel_sources()
    _launch_again_directly()
    if _current is not None:
        _end_program()
    arch_obj = _gpu() if arch == "gpu" else {"cpu": ti.cpu, "cuda": ti.cuda, "vulkan": ti.vulkan, "metal": ti.metal}[arch]
    cache_dir = os.environ.get("CODESIGN_TAICHI_CACHE")  # default: Taichi's own (~/.cache/taichi)
    with contextlib.redirect_stdout(sys.stderr):  # its "Starting on arch=..." line: stdout is for results
        ti.init(
            arch=arch_obj,
            default_fp=ti.f64 if dtype == "float64" else ti.f32,
            default_ip=ti.i32,
            # cfg_optimization stays on (Taichi's default): off, compiles took 40% less time but its reverse
            # mode gave non-finite gradients (docs/log/performance-2026-11.md, "Where a cold suite's compile goes")
            offline_cache=True,
            offline_cache_max_size_of_files=CACHE_LIMIT_BYTES,
            **({"offline_cache_file_path": cache_dir} if cache_dir else {}),
            # `codesign bench engine --profile`; named only when on (named at all, it changes the kernel cache's keys)
            **({"kernel_profiler": True} if os.environ.get("CODESIGN_KERNEL_PROFILER") == "1" else {}),
            log_level=ti.WARN,
        )
    _current = wanted
    generation += 1


def _gpu():
    """`arch: gpu`: the first of CUDA, Metal and Vulkan this machine has, else the CPU with a warning.
    Not Taichi's own `ti.gpu`, whose probe of OpenGL crashes the process on a machine without a
    display (a segmentation fault, no message); the engine does not target OpenGL."""
    import warnings

    from taichi.lang.misc import is_arch_supported

    for arch in (ti.cuda, ti.metal, ti.vulkan):
        if is_arch_supported(arch):
            return arch
    warnings.warn("arch 'gpu': this machine has no CUDA, Metal or Vulkan GPU; running on the CPU", stacklevel=3)
    return ti.cpu


def _memoize_source_positions() -> None:
    """Have Taichi's frontend format each source position once.

    For every AST node it visits, Taichi's frontend formats the node's source excerpt (text wrapped
    with `textwrap`, underlined with carets) to quote in error messages; a `ti.static` loop visits
    its body once per unrolled iteration, so p2g's 27 nodes format the same excerpts 27 times. That
    formatting was half of the frontend's time in a profile of a study's tiny run, and a warm run
    pays the frontend for every kernel of every new storage (docs/log/performance-2026-11.md). The excerpt
    depends only on the node's place in its source, so it is kept per place: the same text, once.
    Taichi versions without this method (`ASTTransformerContext.get_pos_info`) are left alone."""
    from taichi.lang.ast import ast_transformer_utils

    context = getattr(ast_transformer_utils, "ASTTransformerContext", None)
    original = getattr(context, "get_pos_info", None)
    if original is None or getattr(original, "memoized", False):
        return
    excerpts: dict[tuple, str] = {}

    def get_pos_info(self, node) -> str:
        body = getattr(node, "body", None)
        try:
            place = (self.file, self.lineno_offset, self.indent, self.func.func.__name__, type(node).__name__,
                     node.lineno, node.end_lineno, node.col_offset, node.end_col_offset,
                     body[0].lineno if isinstance(body, list) and body else None, self.src[node.lineno - 1])
        except (AttributeError, IndexError, TypeError):
            return original(self, node)
        excerpt = excerpts.get(place)
        if excerpt is None:
            if len(excerpts) >= POSITION_CACHE_LIMIT:
                excerpts.clear()
            excerpt = excerpts[place] = original(self, node)
        return excerpt

    get_pos_info.memoized = True
    context.get_pos_info = get_pos_info


def _memoize_kernel_sources() -> None:
    """Have Taichi's frontend read each function's source once.

    Taichi reads a `ti.func`'s source again every time a kernel inlines it, at every call site of
    every kernel of every new storage; reading it (`inspect.getsourcelines`: the module's lines,
    tokenized to find the function's block) was a fifth of the frontend's time for the quick
    start's kernels (docs/log/performance-2026-11.md). A function object's source does not change,
    so it is kept per function object: a function defined again is a new object, read afresh.
    Taichi versions without these names in `kernel_impl` are left alone."""
    from taichi.lang import kernel_impl

    for name in ("getsourcelines", "getsourcefile"):
        original = getattr(kernel_impl, name, None)
        if original is None or getattr(original, "memoized", False):
            continue
        kept = functools.lru_cache(maxsize=None)(original)
        kept.memoized = True
        setattr(kernel_impl, name, kept)


def data_oriented(cls: type) -> type:
    """`ti.data_oriented`, with the object's other attributes read at Python's own speed.

    Taichi's decorator sends every attribute read of the object through a Python function that
    looks for a kernel to bind (the quick start read its storage's attributes 36,000 times an
    iteration that way). Here only the names of kernels take Taichi's route; any other name is read
    as on any object, which is what Taichi's route returns for it."""
    cls = ti.data_oriented(cls)
    taichi_getattr = cls.__getattribute__

    def is_kernel(value) -> bool:
        return hasattr(value.fget if isinstance(value, property) else value, "_is_wrapped_kernel")

    kernels = frozenset(name for name in dir(cls) if is_kernel(getattr(cls, name)))

    def __getattribute__(self, name: str):
        if name in kernels:
            return taichi_getattr(self, name)
        return object.__getattribute__(self, name)

    cls.__getattribute__ = __getattribute__
    return cls


LAUNCH_PLAN_LIMIT = 1024
"""Launch plans kept per kernel (one per template arguments, so per storage) before starting afresh."""


class _LaunchPlan:
    """How to launch one compiled kernel again: which arguments go to which slot, as which type."""

    __slots__ = ("key", "kernel", "owners", "slots")

    def __init__(self, key: tuple, kernel, owners: tuple, slots: tuple) -> None:
        self.key, self.kernel, self.owners, self.slots = key, kernel, owners, slots


def _launch_again_directly() -> None:
    """Launch a kernel the second time on without Taichi's per-call Python work.

    Taichi 1.7's `Kernel.__call__` works out on every launch what the previous launch with the same
    template arguments already knew: it extracts a key from every argument, looks the compiled
    kernel up and sets each argument through a chain of type tests; a data-oriented kernel with four
    scalar arguments took 24 us a launch on this CPU where the launch itself takes 2.6 (a differentiable
    substep launches about 27 kernels). A kernel whose runtime arguments are all scalars, without a
    return value or a print, is launched from a plan kept per template arguments (by identity for
    objects, by value for numbers): the same compiled kernel, the same arguments, a scalar of the
    wrong type still refused. The plan is used only while Taichi still holds that compiled kernel
    (a destroyed SNode tree or a reset drops it); anything else takes Taichi's own path. Taichi
    versions whose `Kernel` lacks these names are left alone."""
    from taichi.lang import kernel_impl
    from taichi.types import primitive_types
    from taichi.lang.exception import handle_exception_from_cpp

    kernel_class = getattr(kernel_impl, "Kernel", None)
    original = getattr(kernel_class, "__call__", None)
    if original is None or getattr(original, "plans_launches", False) or not hasattr(kernel_class, "ensure_compiled"):
        return
    floats, ints = primitive_types.real_type_ids, primitive_types.integer_type_ids
    # matched by exact type: isinstance would ask a data-oriented object for its __class__ through
    # Taichi's slow __getattribute__
    numbers = frozenset((int, float, bool, str, type(None)))

    def template_key(kernel, args) -> tuple:
        """The template arguments as a key: numbers by value, objects by identity (which the plan
        checks against its weak references: an id can be reused)."""
        return tuple((type(args[i]), args[i]) if type(args[i]) in numbers else id(args[i])
                     for i in kernel.template_slot_locations)

    def make_plan(kernel, args) -> _LaunchPlan | None:
        """The plan for launching `kernel` with arguments like `args`; None where Taichi's path is needed."""
        if kernel.return_type is not None or kernel.has_print:
            return None
        owners, slots, slot = [], [], 0
        for i, (argument, value) in enumerate(zip(kernel.arguments, args)):
            annotation = argument.annotation
            if i in kernel.template_slot_locations:
                if type(value) not in numbers:
                    try:
                        owners.append((i, weakref.ref(value)))
                    except TypeError:
                        return None
                continue
            if id(annotation) in floats:
                slots.append((slot, i, float))
            elif id(annotation) in ints and kernel_impl.is_signed(kernel_impl.cook_dtype(annotation)):
                slots.append((slot, i, int))
            else:
                return None  # arrays, matrices, unsigned: Taichi's path
            slot += 1
        key = kernel.ensure_compiled(*args)
        return _LaunchPlan(key, kernel.compiled_kernels[key], tuple(owners), tuple(slots))

    def launch(plan: _LaunchPlan, args) -> bool:
        """Launch from `plan`; False (nothing launched) where an argument needs Taichi's checks."""
        context = plan.kernel.make_launch_context()
        for slot, i, kind in plan.slots:
            value = args[i]
            if kind is float:
                if not isinstance(value, (float, int, np.floating, np.integer)):
                    return False
                context.set_arg_float((slot,), float(value))
            else:
                if not isinstance(value, (int, np.integer)):
                    return False
                context.set_arg_int((slot,), int(value))
        program = impl.get_runtime().prog
        try:
            program.launch_kernel(program.compile_kernel(program.config(), program.get_device_caps(), plan.kernel),
                                  context)
        except Exception as error:  # Taichi's own path turns a C++ error into its Python one the same way
            raise handle_exception_from_cpp(error) from None
        return True

    def __call__(self, *args, **kwargs):
        runtime = self.runtime
        if kwargs or len(args) != len(self.arguments) or runtime.target_tape or runtime.fwd_mode_manager:
            return original(self, *args, **kwargs)
        plans = self.__dict__.setdefault("_launch_plans", {})
        key = template_key(self, args)
        plan = plans.get(key, False)
        if plan is None:  # planned before: Taichi's path
            return original(self, *args)
        if (plan and self.compiled_kernels.get(plan.key) is plan.kernel
                and all(ref() is args[i] for i, ref in plan.owners) and launch(plan, args)):
            return None
        result = original(self, *args)
        if len(plans) >= LAUNCH_PLAN_LIMIT:
            plans.clear()  # plans of collected storages and ended programs: never used again
        plans[key] = make_plan(self, args)
        return result

    __call__.plans_launches = True
    kernel_class.__call__ = __call__


MAX_SCATTER_COPIES = 4
"""p2g on a CPU scatters each thread's chunk of particles into a private grid (2.5x to 4x faster
than float atomic adds, measured); each copy is a dense grid of 4 floats per node, so their
number is capped: more threads than copies leave the rest idle during p2g."""


def scatter_copies() -> int:
    """Private grids for p2g: one per CPU thread (up to MAX_SCATTER_COPIES); 1 on a GPU, whose
    atomic adds are native (1 means one shared grid with atomic adds). The environment variable
    CODESIGN_SCATTER_COPIES overrides it (benchmarks compare the two scatters with it)."""
    forced = os.environ.get("CODESIGN_SCATTER_COPIES")
    if forced:
        if not forced.isdigit() or int(forced) < 1:
            raise ValueError(f"CODESIGN_SCATTER_COPIES must be a positive integer, got {forced!r}")
        return int(forced)
    if on_gpu():
        return 1
    return max(1, min(impl.current_cfg().cpu_max_num_threads, MAX_SCATTER_COPIES))


FOLD_THREADS = 8192
"""On a GPU a loop that reduces into one value (the particles' box, the guard's maxima) runs on this
many threads, each folding every FOLD_THREADS-th particle before one atomic: Taichi's own reduction
of such a loop ends with an atomic from each thread of a grid sized for the whole GPU (about 5 ms a
substep on an H200 for the box's six, whatever the particle count)."""


def on_gpu() -> bool:
    """Whether Taichi runs on a GPU (not a CPU backend)."""
    return impl.current_cfg().arch not in (ti.x64, ti.arm64)


def _forced(variable: str) -> bool | None:
    """A switch the environment variable forces (1 or 0; benchmarks and tests compare both
    settings on one machine), or None where it is unset."""
    forced = os.environ.get(variable)
    if forced not in (None, "", "0", "1"):
        raise ValueError(f"{variable} must be 0 or 1, got {forced!r}")
    return forced == "1" if forced else None


def fold_reductions() -> bool:
    """Whether reductions into one value fold per thread first (FOLD_THREADS): on a GPU, or where
    the environment variable CODESIGN_FOLD_REDUCTIONS says 1 or 0 (tests compare the two on a CPU)."""
    forced = _forced("CODESIGN_FOLD_REDUCTIONS")
    return on_gpu() if forced is None else forced


SERIAL_PARTICLES = 1024
"""A parallel loop on a CPU costs about 30 us to hand its work to Taichi's threads and wait for
them (2 cores, 2026-11-29: 27 to 33 us for a loop of 1 to 4,096 trivial iterations, against 5 us
run serially), and a substep runs about seven such loops: more than its work on a thousand
particles. A storage's loops therefore run on the launching thread where the work the other
threads would take, capacity x (threads - 1) / threads particles, is at most this many."""


def serial_loops(capacity: int) -> bool:
    """Whether the kernels of a storage of `capacity` particles run their loops serially: on a CPU,
    where the other threads' share of the work is small (SERIAL_PARTICLES), or where the
    environment variable CODESIGN_SERIAL_LOOPS says 1 or 0. Each particle's and node's arithmetic
    is the same either way (p2g's private grids keep their chunks): states come out bit for bit
    alike, gradients to round-off (fast-math compiles a serial loop into its kernel's function)."""
    forced = _forced("CODESIGN_SERIAL_LOOPS")
    if forced is not None:
        return forced
    threads = impl.current_cfg().cpu_max_num_threads
    return not on_gpu() and capacity * (threads - 1) <= SERIAL_PARTICLES * threads


def reset() -> None:
    """Free every field and compiled kernel of this process; the next simulator starts afresh.

    Taichi's offline cache keys kernels by, among others, the ids of the fields they touch,
    which count up in allocation order; starting from a fresh program makes those ids (and so
    cache hits) independent of whatever was simulated before in the process.
    """
    global _current, generation
    if _current is not None:
        _end_program()
        _current = None
        generation += 1
