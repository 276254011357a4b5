"""codesign_mpm.runtime: Taichi set up once, its frontend's source excerpts formatted once per place,
each function's source read once, kernels launched again from a plan, ended programs kept from
freeing a live program's memory, and small storages' loops kept out of the thread pool."""

from types import SimpleNamespace

import pytest
import taichi as ti
from taichi.lang import kernel_impl
from taichi.lang.ast import ast_transformer_utils

from codesign_mpm import runtime


def test_a_compile_error_still_quotes_the_line_at_fault_with_excerpts_kept():
    """The kept excerpts are the ones Taichi would have formatted: two kernels whose errors lie on
    different lines each quote their own line (not an excerpt kept for another node)."""
    runtime.init_taichi("cpu", "float32")
    assert getattr(ast_transformer_utils.ASTTransformerContext.get_pos_info, "memoized", False)
    field = ti.field(float, shape=4)

    @ti.kernel
    def first_fault():
        for i in ti.static(range(2)):
            field[i] = 1.0
        field[0] = undefined_first  # noqa: F821

    @ti.kernel
    def second_fault():
        for i in ti.static(range(2)):
            field[i] = 2.0
        field[1] = undefined_second  # noqa: F821

    for kernel, name in ((first_fault, "undefined_first"), (second_fault, "undefined_second")):
        with pytest.raises(ti.TaichiNameError) as info:
            kernel()
        assert f"field[{0 if name.endswith('first') else 1}] = {name}" in str(info.value)
        assert "^" in str(info.value)  # the excerpt's underline
    runtime.reset()


def test_a_functions_source_is_read_once_however_many_kernels_inline_it():
    """Taichi reads a ti.func's source at every call site; the kept copy serves all but the first.
    It is kept per function object, text only: the same function made again with another value
    (a new object) is read for itself and computes with its own value."""
    runtime.init_taichi("cpu", "float32")
    field = ti.field(float, shape=3)

    def scale_by(factor):
        @ti.func
        def scaled(x):
            return factor * x
        return scaled

    twice = scale_by(2.0)

    @ti.kernel
    def once():
        field[0] = twice(1.0)

    @ti.kernel
    def nested():
        field[1] = twice(twice(1.0))

    before = kernel_impl.getsourcelines.cache_info()
    once()
    nested()
    after = kernel_impl.getsourcelines.cache_info()
    assert (after.misses - before.misses, after.hits - before.hits) == (3, 2)  # two kernels and `scaled` read once
    thrice = scale_by(3.0)

    @ti.kernel
    def redefined():
        field[2] = thrice(1.0)

    redefined()
    assert field.to_numpy().tolist() == [2.0, 4.0, 3.0]
    runtime.reset()


@ti.data_oriented
class _Counter:
    """A data-oriented object with a kernel of scalar arguments and one with a template argument."""

    def __init__(self):
        self.values = ti.field(ti.f32, shape=4)

    @ti.kernel
    def add(self, i: ti.i32, amount: ti.f32):
        self.values[i] += amount

    @ti.kernel
    def add_signed(self, i: ti.i32, negative: ti.template()):
        self.values[i] += -1.0 if ti.static(negative) else 1.0


def _probe_class() -> type:
    """A fresh class with each kind of attribute a storage has: a field, a plain value, a class
    value, a method, a property, its own kernel and an inherited one."""

    class Base:
        @ti.kernel
        def inherited(self, i: ti.i32):
            self.values[i] = 1.0

    class Probe(Base):
        scale = 2.0

        def __init__(self):
            self.values = ti.field(ti.f32, shape=2)
            self.plain = [1, 2]

        @ti.kernel
        def own(self, i: ti.i32):
            self.values[i] = 2.0

        def method(self) -> float:
            return self.scale

        @property
        def doubled(self) -> float:
            return 2 * self.scale

    return Probe


def test_a_data_oriented_objects_attributes_read_as_through_taichis_route():
    """`runtime.data_oriented` sends only kernel names through Taichi's attribute route; every other
    attribute reads as Taichi's route reads it, and the kernels run bound to their object."""
    runtime.init_taichi("cpu", "float32")
    fast, slow = runtime.data_oriented(_probe_class())(), ti.data_oriented(_probe_class())()
    for name in ("values", "plain", "scale", "method", "doubled", "inherited", "own"):
        ours, taichis = getattr(fast, name), getattr(slow, name)
        assert type(ours) is type(taichis), name
        if name in ("inherited", "own"):
            assert ours._kernel_owner is fast and taichis._kernel_owner is slow
        elif name == "method":
            assert ours() == taichis() and ours.__self__ is fast
        elif name != "values":
            assert ours == taichis, name
    fast.own(0)
    fast.inherited(1)
    assert fast.values.to_numpy().tolist() == [2.0, 1.0]
    runtime.reset()


def _taichi_launches(monkeypatch) -> list:
    """Count the launches that take Taichi's own path (a spy on `Kernel.launch_kernel`)."""
    calls = []
    original = kernel_impl.Kernel.launch_kernel
    monkeypatch.setattr(kernel_impl.Kernel, "launch_kernel", lambda self, *a: calls.append(1) or original(self, *a))
    return calls


def test_a_kernel_is_launched_again_from_its_plan_with_the_same_results(monkeypatch):
    """After its first launch, a kernel of scalar arguments skips Taichi's per-call path; each
    object and each template value keeps its own compiled kernel, and a scalar of the wrong type is
    still refused with Taichi's error."""
    runtime.init_taichi("cpu", "float32")
    taichi_path = _taichi_launches(monkeypatch)
    first, second = _Counter(), _Counter()
    for _ in range(3):
        first.add(1, 0.5)
        second.add(2, 2)
        first.add_signed(0, True)
        second.add_signed(0, False)
    assert len(taichi_path) == 4  # each (kernel, object, template value) once; the other 8 from plans
    assert first.values.to_numpy().tolist() == [-3.0, 1.5, 0.0, 0.0]
    assert second.values.to_numpy().tolist() == [3.0, 0.0, 6.0, 0.0]
    with pytest.raises(ti.TaichiRuntimeTypeError, match="i32"):
        first.add(1.5, 1.0)
    assert first.values.to_numpy().tolist() == [-3.0, 1.5, 0.0, 0.0]
    runtime.reset()


def test_a_plan_is_dropped_with_the_compiled_kernel_it_launches(monkeypatch):
    """Destroying an SNode tree makes Taichi drop every compiled kernel (they name its fields); a
    plan of the dropped kernel is not used: the next launch compiles and launches through Taichi."""
    runtime.init_taichi("cpu", "float32")
    counter = _Counter()
    counter.add(0, 1.0)
    builder = ti.FieldsBuilder()
    builder.dense(ti.i, 2).place(ti.field(ti.f32))
    runtime.fields_tree(builder).destroy()
    taichi_path = _taichi_launches(monkeypatch)
    counter.add(0, 1.0)
    counter.add(0, 1.0)
    assert len(taichi_path) == 1
    assert counter.values[0] == 3.0
    runtime.reset()


OUTLIVING_THEIR_PROGRAM = """
import gc, weakref
import taichi as ti
from codesign_mpm import runtime

runtime.init_taichi("cpu", "float32")
builder = ti.FieldsBuilder()
field = ti.field(ti.f32)
builder.dense(ti.i, 1000).place(field)
tree = runtime.fields_tree(builder)
old = [runtime.ndarray(ti.f32, (64,)) for _ in range(2000)]
watch = weakref.ref(old[0])
runtime.reset()  # a new program
runtime.init_taichi("cpu", "float32")
live = [runtime.ndarray(ti.f32, (64,)) for _ in range(2000)]
for array in live:
    array.fill(1.0)
del old, tree, builder, field
gc.collect()
later = [runtime.ndarray(ti.f32, (64,)) for _ in range(2000)]  # would take freed memory
for array in later:
    array.fill(7.0)
print(watch() is not None, sum(not (array.to_numpy() == 1.0).all() for array in live))
"""


def test_ndarrays_and_fields_outliving_their_program_leave_the_next_one_intact():
    """Two ways an ended Taichi program (a simulator collected after a dtype switch, after a test
    module's fresh program, after a sweep's recycled one) could free a live program's memory:
    collecting an ndarray asks the *current* program to free it by its address, which a live
    ndarray may have taken (1-4 of 2000 overwritten); and an SNode tree holds its program, whose
    teardown, when the tree is collected in the next program, frees memory that program uses (a
    segmentation fault in the next kernel). Such ndarrays are never collected and such trees let
    go of their program at its end. In a process of its own: the failure is a crash."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", OUTLIVING_THEIR_PROGRAM], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, f"exit {done.returncode}: {done.stderr[-2000:]}"
    kept, overwritten = done.stdout.splitlines()[-1].split()
    assert kept == "True", "an ndarray of the ended program was collected"
    assert overwritten == "0", f"{overwritten} of 2000 live ndarrays overwritten"


def test_arch_gpu_without_a_gpu_runs_on_the_cpu_with_a_warning_instead_of_crashing():
    """Taichi's own `ti.gpu` probes OpenGL, which kills a process on a machine without a display (a
    segmentation fault); `arch: gpu` takes CUDA, Metal or Vulkan where there is one, else the CPU
    and says so. In a process of its own: it starts a Taichi program."""
    import subprocess
    import sys

    code = ("import taichi as ti; from codesign_mpm import runtime; runtime.init_taichi('gpu'); "
            "print(ti.lang.impl.current_cfg().arch)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    arch = done.stdout.strip().splitlines()[-1]
    assert arch in ("Arch.x64", "Arch.arm64", "Arch.cuda", "Arch.metal", "Arch.vulkan")
    if arch in ("Arch.x64", "Arch.arm64"):
        assert "no CUDA, Metal or Vulkan GPU; running on the CPU" in done.stderr


def test_a_storage_runs_its_loops_serially_where_the_other_threads_would_take_little(monkeypatch):
    """runtime.serial_loops: serial where capacity x (threads - 1) / threads <= SERIAL_PARTICLES,
    always on one thread, never on a GPU; CODESIGN_SERIAL_LOOPS forces it, and names itself when
    it is neither 0 nor 1."""
    def machine(threads, arch=ti.x64):
        config = SimpleNamespace(cpu_max_num_threads=threads, arch=arch)
        monkeypatch.setattr(runtime, "impl", SimpleNamespace(current_cfg=lambda: config))

    assert runtime.SERIAL_PARTICLES == 1024
    machine(2)
    assert runtime.serial_loops(2048) and not runtime.serial_loops(3072)
    machine(16)
    assert runtime.serial_loops(1024) and not runtime.serial_loops(2048)
    machine(1)
    assert runtime.serial_loops(10 ** 6)
    machine(2, ti.cuda)
    assert not runtime.serial_loops(1024)
    monkeypatch.setenv("CODESIGN_SERIAL_LOOPS", "1")
    assert runtime.serial_loops(10 ** 6)
    monkeypatch.setenv("CODESIGN_SERIAL_LOOPS", "0")
    machine(2)
    assert not runtime.serial_loops(1024)
    monkeypatch.setenv("CODESIGN_SERIAL_LOOPS", "yes")
    with pytest.raises(ValueError, match="CODESIGN_SERIAL_LOOPS must be 0 or 1, got 'yes'"):
        runtime.serial_loops(1024)
