"""Gradients through clay and mud (wetland): every input of a rollout, the covers' stress Jacobians and a
muscled clay body, against central finite differences (float64; see gradient_checks.py)."""
import pytest

from gradient_checks import check_every_input, check_muscled_plastic_body, check_stress_jacobian  # same folder: on sys.path under pytest

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("name", ['clay', 'wetland'])
def test_every_input_gradient_matches_finite_differences(name):
    check_every_input(name)


@pytest.mark.parametrize("name", ['clay', 'wetland'])
def test_stress_jacobian_matches_finite_differences(name):
    check_stress_jacobian(name)


@pytest.mark.parametrize("muscle_model", ["active", "energy"])
def test_a_muscled_clay_body_matches_finite_differences(muscle_model):
    check_muscled_plastic_body(muscle_model)


def test_a_muscled_mud_body_matches_finite_differences():
    check_muscled_plastic_body("active", "mud")
