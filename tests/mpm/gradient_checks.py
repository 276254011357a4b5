"""Gradient checks through every material against central finite differences (float64), shared
by the test_gradients_*.py files (one per group of environments, so pytest-xdist compiles
their backward kernels in parallel).

For the elastic robot alone (ground) and on each ground cover (sand, clay, mud, snow, water),
everything a rollout differentiates (actions, volume, Young's modulus, muscle membership,
fibre, x0, v0, C0 and, in snow, J_p0) is checked from the environment's settled start (cover and robot at rest, the cover
carrying its own weight) over enough frames that the cover carries the robot's.
Each plastic cover's stress Jacobian is then checked on its own: one substep from rest with
the cover held at a chosen deformation (F = I or confined, where eigenvalues coincide;
uniaxial compression; a generic F), differentiated with respect to the initial F.

One simulator layout per environment: the first check compiles the backward kernels (a few
minutes each on a cold cache), and the Jacobian check reuses them from the pool.
"""
from dataclasses import replace

import numpy as np
import pytest

from codesign_mpm import BodySpec, MaterialSpec, MuscleSpec, Scene, ShapeSpec, TerrainSpec, build_particles
from codesign_mpm.engine import Simulator
from test_environments import NARROW, make_env, random_actions  # same folder: pytest puts it on sys.path


COVERS = {"ground": None, "ice": None, "desert": "sand", "clay": "clay", "wetland": "mud", "snow": "snow",
          "shallow_water": "water", "ocean": "water"}
T = 8  # frames: the cover has settled onto the terrain and carries the robot
MAX_FRAMES, SEGMENT = 12, 64  # shared by both simulators of an environment, so they share compiled kernels
MUSCLE_STEP = 1e-4
FOOT_STEP = 1e-5  # relative, for the foot's Young's modulus and fibre direction
"""Steps where the central difference has converged and round-off has not yet set in. A foot's
membership in a muscle moves the loss by ~1e-6 per unit: on Perlin terrain 1.49689e-6 at a step
of 1e-6 against the adjoint's 1.49638e-6, 1.49641e-6 and 1.496377e-6 at 1e-5 and 1e-4; clay's
foot (a plastic body: kinks) wants the small end, 5.24164e-6 at 1e-4 and 1e-5, 5.24977e-6 at 1e-3.
With docs/log/contact.md section 14's surface contact the foot's fibre at a step of 1e-6 gives 1.52348e-6 against
the adjoint's 1.52381e-6; ground's foot at 1e-5, 1e-4 (Young's modulus, relative): 1.668357e-10,
1.668389e-10 against 1.668389e-10. A cover particle's Young's modulus keeps a relative 1e-6
(mud's yield kinks at 1e-5)."""


def central(f, eps: float) -> float:
    return (f(eps) - f(-eps)) / (2 * eps)


def assert_matches(analytic: float, numeric: float, scale: float, what) -> None:
    """Relative 1e-4, or 1e-4 of the scale of that input's gradient for entries far below it."""
    assert analytic == pytest.approx(numeric, rel=1e-4, abs=1e-4 * scale), (what, analytic, numeric, scale)


def make_check_env(name: str, dtype: str = "float64", **overrides):
    """A covered environment in the NARROW domain (half its cover particles); a bare one keeps the
    presets' width, so test_designs_env's ground simulator shares its compiled layout."""
    return make_env(name, dtype=dtype, **({"size": NARROW} if COVERS[name] else {}), **overrides)


def check_every_input(name: str, **overrides) -> None:
    """`overrides`: the environment config's (e.g. a Perlin terrain, a viscous cover)."""
    env = make_check_env(name, **overrides)
    sim = Simulator(env.scene, env.particles, requires_grad=True, max_frames=MAX_FRAMES, checkpoint_every=SEGMENT)
    p = env.particles
    rng = np.random.default_rng(2)
    actions = random_actions(env, T, seed=1)
    w_com, wx = rng.normal(size=(T + 1, 3)), rng.normal(size=(p.n, 3)) / p.n
    sim.set_initial_state(**env.initial_state(p))  # the environment's settled start: the cover at rest
    start = sim.snapshot()

    def loss(a=actions) -> float:
        out = sim.rollout(a, checkpoint_every=7)
        return float((w_com * out.com_x).sum() + (wx * out.x).sum())

    try:
        loss()
        g = sim.backward(com_x=w_com, x=wx)
        robot, cover = np.flatnonzero(p.robot), np.flatnonzero(~p.robot)
        foot = robot[np.argmin(p.x[robot, 1])]  # a robot particle on the ground (or in the cover)
        cases = [("actions", (0, 0), 1e-6), ("actions", (T - 1, 3), 1e-6), ("volume", foot, 1e-5 * p.volume[foot]),
                 ("youngs_modulus", foot, FOOT_STEP * p.youngs_modulus[foot]), ("muscle", (foot, 1), MUSCLE_STEP),
                 ("fiber", (foot, 1), FOOT_STEP), ("x0", (foot, 0), 1e-6), ("v0", (foot, 1), 1e-6),
                 ("C0", (foot, 0, 1), 1e-4)]
        if len(cover):
            assert np.abs(g.x0[cover]).max() > 0, "the cover should influence the loss"
            under = cover[np.argmax(np.abs(g.v0[cover]).sum(1))]  # the cover particle that matters most
            cases += [("x0", (under, 1), 1e-6), ("v0", (under, 0), 1e-6), ("volume", under, 1e-5 * p.volume[under]),
                      ("C0", (under, 1, 0), 1e-4)]  # the closed-loop bridge carries C between frames
            if COVERS[name] != "water":  # water's stiffness is its bulk modulus, not E
                cases.append(("youngs_modulus", under, 1e-6 * p.youngs_modulus[under]))
            if COVERS[name] == "snow":  # snow's plastic volume ratio is state too (settled: compacted)
                cases.append(("Jp0", under, 1e-6))
        if g.u0 is not None:  # the spring contact's tangential springs are state too
            cases += [("u0", (foot, 0), 1e-6), ("u0", (foot, 2), 1e-6)]

        def perturbed(field, index, eps):
            sim.restore(start)
            if field == "actions":
                a = actions.copy()
                a[index] += eps
                return loss(a)
            if field in ("C0", "Jp0", "u0"):
                value = {"C0": lambda: np.zeros((p.n, 3, 3)), "u0": lambda: np.zeros((p.n, 3)),
                         "Jp0": lambda: env.initial_state(p)["Jp"].copy()}[field]()
                value[index] += eps
                sim.set_initial_state(**{field[:-1]: value})
                return loss()
            source = {"x0": "x", "v0": "v"}.get(field, field)
            value = getattr(p, source).copy()
            value[index] += eps
            if field in ("x0", "v0"):
                sim.set_initial_state(**{source: value})
            else:
                sim.set_design(**{field: value})
            return loss()

        for field, index, eps in cases:
            numeric = central(lambda e: perturbed(field, index, e), eps)
            gradient = getattr(g, field)
            assert_matches(gradient[index], numeric, np.abs(gradient).max(), (name, field, index))
    finally:
        sim.close()
        env.close()


CONFINED = np.diag([0.99, 0.99, 0.99])
FD_STEP_F = 1e-5
"""Above the eigen-gap blending width (engine.JACOBI_EPS, 1e-6): the forward pass then takes the true
divided differences at coincident eigenvalues while the adjoint uses the blended slope, so a wrong
slope at coincidence shows (a step below the width takes the same branch on both sides)."""
STATES = {
    "rest": np.eye(3),  # three equal eigenvalues
    "compressed": np.diag([1.0, 0.97, 1.0]),  # uniaxial: x and z equal; clay and mud yield, snow clamps
    "generic": 0.985 * np.eye(3) + 0.01 * np.random.default_rng(5).normal(size=(3, 3)),
}


def check_stress_jacobian(name: str) -> None:
    """d loss / d F0 after one substep goes through the cover's stress and return mapping."""
    env = make_check_env(name)
    scene = replace(env.scene, gravity=[0.0, 0.0, 0.0], frame_dt=1e-5)  # one substep per frame
    sim = Simulator(scene, env.particles, requires_grad=True, max_frames=MAX_FRAMES, checkpoint_every=SEGMENT)
    p = env.particles
    cover = np.flatnonzero(~p.robot)
    rng = np.random.default_rng(3)
    wv, wF = rng.normal(size=(p.n, 3)), rng.normal(size=(p.n, 3, 3))
    try:
        assert sim.timestep.substeps == 1
        for state, F_cover in STATES.items():
            if name == "desert" and state == "rest":
                F_cover = CONFINED  # sand at F = I sits on its apex (no cohesion): not differentiable there
            F0 = np.tile(np.eye(3), (p.n, 1, 1))
            F0[cover] = F_cover
            # a particle of the cover's top layer, away from the robot and the walls
            top = cover[p.x[cover, 1] >= p.x[cover, 1].max() - 1e-9]
            probe = top[np.argmin(np.abs(p.x[top][:, [0, 2]] - [0.45, 0.25]).sum(1))]

            def loss(F) -> float:
                # everything drifts up slowly: terrain contact (and its friction) has a kink at zero
                # normal velocity, where a state at rest would sit (measured: FD then averages the two
                # one-sided slopes, 0.2-0.9% off the adjoint's; with the drift they agree to 1e-9)
                sim.set_initial_state(F=F, v=np.tile([0.0, 0.05, 0.0], (p.n, 1)))
                out = sim.rollout(np.zeros((1, env.action_dim)))
                _, _, _, F_end = sim.particles_state()
                return float((wv * out.v).sum() + (wF * F_end).sum())

            loss(F0)
            analytic = sim.backward(v=wv, F=wF).F0[probe]
            numeric = np.zeros((3, 3))
            for i in range(3):
                for j in range(3):
                    def shifted(e):
                        F = F0.copy()
                        F[probe, i, j] += e
                        return loss(F)
                    numeric[i, j] = central(shifted, FD_STEP_F)
            np.testing.assert_allclose(analytic, numeric, rtol=1e-4, atol=1e-6 * np.abs(numeric).max(),
                                       err_msg=f"{name} at {state}")
    finally:
        sim.close()
        env.close()


MUSCLED_BODIES = {
    "clay": MaterialSpec(kind="clay", youngs_modulus=1e4, yield_stress=100.0),
    "sand": MaterialSpec(kind="sand", youngs_modulus=1e4, friction_angle=30.0, cohesion=20.0),
    "snow": MaterialSpec(kind="snow", youngs_modulus=1e4),
    "mud": MaterialSpec(kind="mud", youngs_modulus=1e4, poisson_ratio=0.3, yield_stress=50.0, viscosity=1.0),
}


def check_muscled_plastic_body(muscle_model: str, kind: str = "clay") -> None:
    """A robot of a plastic material with muscles (yielding under them): the hand-written reverse of
    the return mapping carries the muscle stress's gradients (action, membership, fibre, stiffness)
    through the projected F, for either muscle model."""
    scene = Scene(size=[1.0, 0.5, 0.5], dx=1 / 32, dtype="float64", muscle_model=muscle_model,
                  terrain=TerrainSpec(kind="flat", height=0.1, friction=0.5),
                  bodies=[BodySpec(name="robot", robot=True, shape=ShapeSpec(size=[0.16, 0.08, 0.08]),
                                   center=[0.5, 0.0, 0.25], rest_on_terrain=True, material=MUSCLED_BODIES[kind],
                                   muscles=MuscleSpec(groups=[2, 2, 1]))])
    p = build_particles(scene)
    sim = Simulator(scene, p, requires_grad=True, max_frames=MAX_FRAMES, checkpoint_every=SEGMENT)
    rng = np.random.default_rng(4)
    steps = 4
    actions = rng.uniform(-0.3, 0.3, size=(steps, p.n_actuators))
    w_com, wx = rng.normal(size=(steps + 1, 3)), rng.normal(size=(p.n, 3)) / p.n
    design = {k: getattr(p, k).copy() for k in ("youngs_modulus", "muscle", "fiber")}

    def loss(a=actions, **changed) -> float:
        sim.set_design(**{**design, **changed})
        out = sim.rollout(a, checkpoint_every=5)
        return float((w_com * out.com_x).sum() + (wx * out.x).sum())

    def shifted(field, index, eps):
        if field == "actions":
            a = actions.copy()
            a[index] += eps
            return loss(a)
        value = design[field].copy()
        value[index] += eps
        return loss(**{field: value})

    try:
        loss()
        assert np.abs(sim.particles_state()[3] - np.eye(3)).max() > 1e-3, "the muscles should deform the body"
        g = sim.backward(com_x=w_com, x=wx)
        worked = int(np.argmax(np.abs(g.muscle).sum(1)))  # the particle whose muscle matters most
        for field, index, eps in [("actions", (0, 1), 1e-6), ("actions", (steps - 1, 3), 1e-6),
                                  ("muscle", (worked, 0), 1e-6), ("fiber", (worked, 2), 1e-6),
                                  ("youngs_modulus", worked, 1e-6 * p.youngs_modulus[worked])]:
            gradient = getattr(g, field)
            assert_matches(gradient[index], central(lambda e: shifted(field, index, e), eps),
                           np.abs(gradient).max(), (kind, muscle_model, field, index))
    finally:
        sim.close()


def check_float32_against_float64(name: str) -> None:
    """The default precision's gradients point where float64's do (cosine > 0.99 for actions,
    Young's modulus and x0 over the whole episode), through the early-stopping eigen-solve, which
    only float32 exercises (its tolerance is 64 round-offs of b's trace)."""
    grads = {}
    for dtype in ("float64", "float32"):
        env = make_check_env(name, dtype=dtype)
        sim = Simulator(env.scene, env.particles, requires_grad=True, max_frames=MAX_FRAMES, checkpoint_every=SEGMENT)
        try:
            sim.set_initial_state(**env.initial_state(env.particles))
            actions = random_actions(env, T, seed=1)
            w_com = np.random.default_rng(7).normal(size=(T + 1, 3))
            sim.rollout(actions, checkpoint_every=7)
            grads[dtype] = sim.backward(com_x=w_com)
        finally:
            sim.close()
            env.close()
    for field in ("actions", "youngs_modulus", "x0"):
        a, b = (np.ravel(getattr(grads[d], field)) for d in ("float64", "float32"))
        cosine = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
        assert cosine > 0.99, (name, field, cosine)
