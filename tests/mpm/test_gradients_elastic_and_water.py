"""Gradients through the elastic robot alone (ground, ice) and in water (shallow water, ocean): every input of a rollout, and the covers' stress Jacobians,
against central finite differences (float64; see gradient_checks.py)."""
import pytest

from codesign_mpm.environment.config import CoverConfig, TerrainConfig
from gradient_checks import check_every_input, check_stress_jacobian  # same folder: on sys.path under pytest

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("name", ['ground', 'ice', 'shallow_water', 'ocean'])
def test_every_input_gradient_matches_finite_differences(name):
    check_every_input(name)


@pytest.mark.parametrize("name", ['shallow_water'])
def test_stress_jacobian_matches_finite_differences(name):
    check_stress_jacobian(name)


VARIANTS = {
    # the terrain's height and normals vary from column to column: contact and friction along slopes
    "ground on Perlin terrain": ("ground", dict(terrain=TerrainConfig(kind="perlin", height=0.1, amplitude=0.03,
                                                                      frequency=6.0, friction=0.5))),
    # the FLIP share (opt-in): its terms in p2g's and g2p's hand adjoints, with contact and friction
    "ground with the FLIP share": ("ground", dict(flip=0.99, terrain=TerrainConfig(kind="perlin", height=0.1,
                                                                                  amplitude=0.03, frequency=6.0,
                                                                                  friction=0.5))),
    # the surface contact (opt-in): its impulse and scatter kernels' adjoints and p2g's term, on a slope with FLIP
    "ground with the surface contact": ("ground", dict(flip=0.99, terrain=TerrainConfig(
        kind="perlin", height=0.1, amplitude=0.03, frequency=6.0, friction=0.5, contact="surface"))),
    # the spring contact (opt-in): its impulse kernel's adjoint, the springs carried between substeps and
    # segments (u0), on a slope with FLIP's share per unit time
    "ground with the spring contact": ("ground", dict(flip=0.99, pic_time=0.265, terrain=TerrainConfig(
        kind="perlin", height=0.1, amplitude=0.03, frequency=6.0, friction=0.5, contact="spring"))),
    # ... every contact stuck (mu 5: the springs follow the contact points), every contact slipping (mu 0.02: the
    # springs at Coulomb's bound)
    "the spring contact sticking": ("ground", dict(pic_time=0.265, terrain=TerrainConfig(
        height=0.1, friction=5.0, contact="spring"))),
    "the spring contact slipping": ("ground", dict(pic_time=0.265, terrain=TerrainConfig(
        height=0.1, friction=0.02, contact="spring"))),
    # every preset's water is inviscid: the viscous stress's gradient otherwise goes unchecked
    "viscous shallow water": ("shallow_water", dict(cover=CoverConfig(kind="water", thickness=0.05,
                                                                      bulk_modulus=1e5, viscosity=20.0))),
}


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_every_input_gradient_matches_finite_differences_on_variants(variant):
    name, overrides = VARIANTS[variant]
    check_every_input(name, **overrides)
