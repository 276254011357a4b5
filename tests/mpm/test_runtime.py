"""codesign_mpm.runtime: Taichi set up once, its frontend's source excerpts formatted once per place."""
import pytest
import taichi as ti
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
