"""Mud: saturated soil, nearly incompressible, clay's von Mises yield plus a Newtonian viscosity
J eta (grad v + grad v^T) (APIC's C as grad v, added by the engine). Parameter vector:
[yield stress, viscosity]."""
from codesign_mpm.materials.base import MaterialModel, Parameter
from codesign_mpm.materials.clay import YIELD_STRESS, return_map

VISCOSITY = Parameter("viscosity", 0.0, lambda v: v >= 0, "must be >= 0", "dynamic viscosity (water, mud)")

MODEL = MaterialModel("mud", "saturated soil: nearly incompressible, von Mises yield plus viscosity", kind="hencky",
                      parameters=(YIELD_STRESS, VISCOSITY), viscosity_index=1, return_map=return_map)
