"""Stresses against closed forms (float64, forward): the three elastic models under uniaxial
stretch and simple shear, and both muscle models (active: its formula and no force at zero
action; energy: the derivative of its energy)."""
import math

import numpy as np
import pytest

from codesign_mpm import BodySpec, MaterialSpec, MuscleSpec, Scene, ShapeSpec, TerrainSpec, build_particles
from codesign_mpm.engine import Simulator
from codesign_mpm.materials import drucker_prager_alpha, lame

E, NU, RATIO = 1.0e4, 0.2, 0.4
MU, LA = lame(E, NU)
FIBER = np.array([1.0, 2.0, 2.0]) / 3.0


def block(model: str = "neo_hookean", muscle_model: str = "active") -> Simulator:
    scene = Scene(size=[0.5, 0.5, 0.5], dx=1 / 32, dtype="float64", gravity=[0.0, 0.0, 0.0],
                  terrain=TerrainSpec(kind="none"), muscle_model=muscle_model,
                  bodies=[BodySpec(shape=ShapeSpec(size=[0.1, 0.1, 0.1]), center=[0.25, 0.25, 0.25],
                                   material=MaterialSpec(kind=model, youngs_modulus=E, poisson_ratio=NU),
                                   muscles=MuscleSpec(groups=[1, 1, 1], fiber=FIBER.tolist(), stiffness_ratio=RATIO))])
    return Simulator(scene, build_particles(scene))


def stress_at(sim: Simulator, F: np.ndarray, action: float = 0.0) -> np.ndarray:
    sim.set_initial_state(F=np.tile(F, (sim.n, 1, 1)))
    tau = sim.stress(np.array([action]))
    np.testing.assert_allclose(tau, np.tile(tau[0], (sim.n, 1, 1)), rtol=0, atol=1e-9)  # uniform F, uniform stress
    return tau[0]


def uniaxial(stretch: float) -> np.ndarray:
    return np.diag([stretch, 1.0, 1.0])


def shear(gamma: float) -> np.ndarray:
    F = np.eye(3)
    F[0, 1] = gamma
    return F


def closed_form(model: str, kind: str, q: float) -> np.ndarray:
    """Kirchhoff stress written out by hand for F = diag(s, 1, 1) or the simple shear e_x (x) e_y gamma."""
    tau = np.zeros((3, 3))
    if kind == "uniaxial":
        s = q
        if model == "neo_hookean":  # mu (F F^T - I) + lambda log(J) I
            tau[0, 0], tau[1, 1] = MU * (s * s - 1) + LA * math.log(s), LA * math.log(s)
        elif model == "corotated":  # R = I: 2 mu (F - I) F^T + lambda (J - 1) J I
            tau[0, 0], tau[1, 1] = 2 * MU * (s - 1) * s + LA * (s - 1) * s, LA * (s - 1) * s
        else:  # StVK: Green strain G_xx = (s^2 - 1) / 2; tau = F (2 mu G + lambda tr G I) F^T
            g = (s * s - 1) / 2
            tau[0, 0], tau[1, 1] = s * s * (2 * MU + LA) * g, LA * g
        tau[2, 2] = tau[1, 1]
        return tau
    g = q  # simple shear, J = 1
    if model == "neo_hookean":  # F F^T - I = [[g^2, g, 0], [g, 0, 0], [0, 0, 0]]
        tau[0, 0], tau[0, 1], tau[1, 0] = MU * g * g, MU * g, MU * g
    elif model == "corotated":  # the rotation of simple shear turns by atan(g / 2) about z
        c = 1 / math.sqrt(1 + g * g / 4)
        R = np.array([[c, c * g / 2, 0], [-c * g / 2, c, 0], [0, 0, 1]])
        F = shear(g)
        tau = 2 * MU * (F - R) @ F.T
    else:  # G = [[0, g/2], [g/2, g^2/2]], tr G = g^2 / 2
        F = shear(g)
        G = np.array([[0, g / 2, 0], [g / 2, g * g / 2, 0], [0, 0, 0]])
        tau = F @ (2 * MU * G + LA * g * g / 2 * np.eye(3)) @ F.T
    return tau


@pytest.mark.parametrize("model", ["neo_hookean", "corotated", "stvk"])
def test_elastic_models_match_their_closed_forms_in_stretch_and_shear(model):
    sim = block(model)
    try:
        for kind, q in (("uniaxial", 1.2), ("uniaxial", 0.85), ("shear", 0.3)):
            F = uniaxial(q) if kind == "uniaxial" else shear(q)
            # 1e-8: Taichi's 3x3 polar decomposition (corotated) converges to about 1e-9 relative
            np.testing.assert_allclose(stress_at(sim, F), closed_form(model, kind, q), rtol=1e-8, atol=1e-6,
                                       err_msg=f"{model} {kind} {q}")
    finally:
        sim.close()


def test_active_muscle_adds_s_a_ff_and_nothing_at_zero_action():
    sim = block()
    try:
        F = shear(0.25) @ uniaxial(1.1)
        passive = stress_at(sim, F)
        np.testing.assert_allclose(passive, closed_neo_hookean(F), rtol=1e-10, atol=1e-8)  # zero action: no force
        Ff = F @ FIBER
        for a in (0.3, -0.2):
            np.testing.assert_allclose(stress_at(sim, F, a) - passive, RATIO * E * a * np.outer(Ff, Ff),
                                       rtol=1e-10, atol=1e-8)
        # a > 0 is a tension along the fibre (it contracts the muscle)
        assert FIBER @ (stress_at(sim, np.eye(3), 0.3)) @ FIBER > 0
    finally:
        sim.close()


def closed_neo_hookean(F: np.ndarray) -> np.ndarray:
    return MU * (F @ F.T - np.eye(3)) + LA * math.log(np.linalg.det(F)) * np.eye(3)


def test_energy_muscle_stress_is_the_derivative_of_its_energy():
    """tau = dpsi/dF F^T with psi = s (|F f|^2 - 1 + a)^2, the derivative taken by central differences."""
    sim = block(muscle_model="energy")
    s, a, h = RATIO * E, 0.2, 1e-6
    F = shear(0.2) @ uniaxial(1.05)

    def psi(G):
        Gf = G @ FIBER
        return s * (Gf @ Gf - 1 + a) ** 2

    P = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            dF = np.zeros((3, 3))
            dF[i, j] = h
            P[i, j] = (psi(F + dF) - psi(F - dF)) / (2 * h)
    try:
        muscle = stress_at(sim, F, a) - closed_neo_hookean(F)
        np.testing.assert_allclose(muscle, P @ F.T, rtol=1e-6, atol=1e-6 * s)
        # at the rest length sqrt(1 - a) the energy form is force-free
        rest = np.eye(3) + (math.sqrt(1 - a) - 1) * np.outer(FIBER, FIBER)
        np.testing.assert_allclose(stress_at(sim, rest, a) - closed_neo_hookean(rest), 0, atol=1e-8)
    finally:
        sim.close()


def test_time_step_counts_only_what_the_muscle_model_adds():
    """Energy: 8 s on the axial modulus; active: 2 s max_action; no muscle: the body alone."""
    def speed(**scene_options) -> float:
        scene = Scene(size=[0.5, 0.5, 0.5], dx=1 / 32, terrain=TerrainSpec(kind="none"), **scene_options,
                      bodies=[BodySpec(shape=ShapeSpec(size=[0.1, 0.1, 0.1]), center=[0.25, 0.25, 0.25],
                                       material=MaterialSpec(youngs_modulus=E, poisson_ratio=NU),
                                       muscles=MuscleSpec(groups=[1, 1, 1], stiffness_ratio=RATIO))])
        from codesign_mpm.engine import time_step
        step = time_step(scene, build_particles(scene))
        return scene.cfl * scene.dx / step.stable_dt

    body = LA + 2 * MU
    assert speed(muscle_model="energy") == pytest.approx(math.sqrt((body + 8 * RATIO * E) / 1e3))
    assert speed(muscle_model="active", max_action=0.3) == pytest.approx(math.sqrt((body + 0.6 * RATIO * E) / 1e3))


def test_actuation_beyond_the_admissible_stress_is_refused():
    """At the action bound the active stress must stay within MAX_ACTIVE_STRESS_RATIO (0.3) of the
    shear modulus mu = E / (2 (1 + nu)): stronger muscles tear bodies, so the scene is refused and
    the message names the largest admissible stiffness_ratio, 0.3 / (max_action 2 (1 + nu))."""
    from codesign_mpm import SceneError

    scene = Scene(size=[0.5, 0.5, 0.5], dx=1 / 32, terrain=TerrainSpec(kind="none"), max_action=1.0,
                  bodies=[BodySpec(shape=ShapeSpec(size=[0.1, 0.1, 0.1]), center=[0.25, 0.25, 0.25],
                                   material=MaterialSpec(youngs_modulus=E, poisson_ratio=NU),
                                   muscles=MuscleSpec(groups=[1, 1, 1], stiffness_ratio=RATIO))])
    with pytest.raises(SceneError, match=r"stiffness_ratio = 0.4 is invalid with max_action = 1.0 .* "
                                         r"stiffness_ratio <= 0.125 for Poisson's ratio 0.2"):
        Simulator(scene, build_particles(scene))
    scene.max_action = 0.3  # 0.4 x 0.3 x 2.4 = 0.288: admissible
    Simulator(scene, build_particles(scene)).close()


def hencky_reference(kind: str, F: np.ndarray, params: dict, E: float = 1e5, nu: float = 0.2) -> np.ndarray:
    """Kirchhoff stress after the return mapping, by SVD in numpy: the plastic models as their
    papers write them (Klar et al. 2016 for sand, von Mises for clay and mud, Stomakhin et al. 2013
    for snow), independent of the engine's eigenframe algebra."""
    mu, la = lame(E, nu)
    U, sigma, _ = np.linalg.svd(F)
    eps = np.log(sigma)
    tr, dev = eps.sum(), eps - eps.sum() / 3
    if kind == "sand":
        slope = drucker_prager_alpha(params["friction_angle"]) * (3 * la + 2 * mu) / (2 * mu)
        if tr > 0:
            eps = np.zeros(3)
        elif np.linalg.norm(dev) > -slope * tr:
            eps = tr / 3 + (-slope * tr) / np.linalg.norm(dev) * dev
    elif kind in ("clay", "mud"):
        radius = math.sqrt(2 / 3) * params["yield_stress"] / (2 * mu)
        if np.linalg.norm(dev) > radius:
            eps = tr / 3 + radius / np.linalg.norm(dev) * dev
    if kind == "snow":
        clamped = np.clip(sigma, 1 - params["critical_compression"], 1 + params["critical_stretch"])
        jp = np.prod(sigma) / np.prod(clamped)
        h = np.clip(math.exp(params["hardening"] * (1 - jp)), 0.1, params["max_hardening"])
        return U @ np.diag(h * (mu * (clamped ** 2 - 1) + la * np.log(clamped).sum())) @ U.T
    return U @ np.diag(2 * mu * eps + la * eps.sum()) @ U.T


PLASTIC = {"sand": dict(friction_angle=30.0), "clay": dict(yield_stress=200.0),
           "mud": dict(yield_stress=30.0, viscosity=0.0),
           "snow": dict(critical_compression=2.5e-2, critical_stretch=7.5e-3, hardening=10.0, max_hardening=10.0)}


@pytest.mark.parametrize("kind", list(PLASTIC))
@pytest.mark.parametrize("gamma", [1e-4, 3e-3, 3e-2])
def test_plastic_stress_in_simple_shear_matches_an_svd_reference(kind, gamma):
    """F = I + gamma e_x (x) e_y, from nearly coincident eigenvalues of b (gamma 1e-4, where the
    engine's eigenframe algebra blends its divided differences) to yielding (clay, mud, snow at 3e-2):
    the engine's stress equals an SVD reference of the return mapping the papers write."""
    scene = Scene(size=[0.5, 0.5, 0.5], dx=1 / 32, dtype="float64", gravity=[0.0, 0.0, 0.0],
                  terrain=TerrainSpec(kind="none"),
                  bodies=[BodySpec(shape=ShapeSpec(size=[0.1, 0.1, 0.1]), center=[0.25, 0.25, 0.25],
                                   material=MaterialSpec(kind=kind, youngs_modulus=1e5, poisson_ratio=0.2,
                                                         **PLASTIC[kind]))])
    sim = Simulator(scene, build_particles(scene))
    try:
        F = shear(gamma)
        if kind == "sand":
            F = F @ np.diag([0.98, 0.98, 0.98])  # confined: inside the cone up to its friction
        expected = hencky_reference(kind, F, PLASTIC[kind])
        np.testing.assert_allclose(stress_at(sim, F), expected, rtol=1e-6, atol=1e-9 * np.abs(expected).max())
        assert abs(expected[0, 1]) > 0
    finally:
        sim.close()
