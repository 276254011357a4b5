"""Gradients through sand (desert) and snow: every input of a rollout, the covers' stress Jacobians and
muscled sand and snow bodies against central finite differences (float64), and float32's gradients
against float64's (see gradient_checks.py)."""
import pytest

from gradient_checks import (check_every_input, check_float32_against_float64, check_muscled_plastic_body,  # same folder
                             check_stress_jacobian)

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("name", ['desert', 'snow'])
def test_every_input_gradient_matches_finite_differences(name):
    check_every_input(name)


@pytest.mark.parametrize("name", ['desert', 'snow'])
def test_stress_jacobian_matches_finite_differences(name):
    check_stress_jacobian(name)


@pytest.mark.parametrize("kind", ["sand", "snow"])
def test_a_muscled_body_matches_finite_differences(kind):
    check_muscled_plastic_body("active", kind)


@pytest.mark.parametrize("name", ["desert", "snow"])
def test_float32_gradients_point_where_float64_ones_do(name):
    check_float32_against_float64(name)
