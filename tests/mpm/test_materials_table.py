"""The materials table of docs/materials.md is the one the material modules build."""
from pathlib import Path

from codesign_mpm.materials import table

DOCS = Path(__file__).parents[2] / "docs" / "materials.md"


def test_the_docs_hold_the_table_the_modules_build():
    text = DOCS.read_text()
    start, end = text.index(table.BEGIN) + len(table.BEGIN), text.index(table.END)
    assert text[start:end].strip() == table.builtin_table(), \
        "regenerate it: python -m codesign_mpm.materials.table --write docs/materials.md"
