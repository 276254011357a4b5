"""Gradients through sand (desert) and snow: every input of a rollout, and the covers' stress Jacobians,
against central finite differences (float64; see gradient_checks.py)."""
import pytest

from gradient_checks import check_every_input, check_stress_jacobian  # same folder: on sys.path under pytest

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("name", ['desert', 'snow'])
def test_every_input_gradient_matches_finite_differences(name):
    check_every_input(name)


@pytest.mark.parametrize("name", ['desert', 'snow'])
def test_stress_jacobian_matches_finite_differences(name):
    check_stress_jacobian(name)
