"""The materials table of docs/materials.md, built from the registered models' modules.

    python -m codesign_mpm.materials.table            # print it (plugins' models included)
    python -m codesign_mpm.materials.table --write docs/materials.md   # replace it between the markers

tests/mpm/test_materials_table.py checks that the docs hold the table of the engine's own models.
"""
from __future__ import annotations

import sys
from pathlib import Path

from codesign_mpm.materials import BUILTIN, MATERIALS, MaterialModel, load_plugin_materials

BEGIN = "<!-- materials table: python -m codesign_mpm.materials.table --write docs/materials.md -->"
END = "<!-- end of the materials table -->"


def _number(value: float) -> str:
    return f"{value:g}"


def row(model: MaterialModel) -> str:
    parameters = ", ".join(f"`{p.name}` {_number(p.default)} ({p.allowed})" for p in model.parameters) or "-"
    extra = {"elastic": "elastic", "hencky": "elastoplastic (Hencky)", "fluid": "fluid"}[model.kind]
    notes = "; forward only" if not model.differentiable else ""
    notes += "; viscous" if model.viscous else ""
    notes += "; J_p is state" if model.plastic_volume else ""
    return (f"| `{model.name}` | {model.id} | {extra}{notes} | {model.description} | {parameters} | "
            f"`codesign_mpm.materials.{model.name}` |" if model.name in BUILTIN else
            f"| `{model.name}` | {model.id} | {extra}{notes} | {model.description} | {parameters} | plugin |")


def table(models: list[MaterialModel] | None = None) -> str:
    models = models if models is not None else list(MATERIALS.values())
    head = ["| kind | id | model | description | parameters (default, valid) | module |",
            "|---|---|---|---|---|---|"]
    return "\n".join(head + [row(m) for m in models])


def builtin_table() -> str:
    return table([MATERIALS[name] for name in BUILTIN])


def write(path: Path) -> None:
    text = path.read_text()
    start, end = text.index(BEGIN) + len(BEGIN), text.index(END)
    path.write_text(text[:start] + "\n" + builtin_table() + "\n" + text[end:])


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--write":
        write(Path(sys.argv[2]))
    else:
        load_plugin_materials()
        print(table())
