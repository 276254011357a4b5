"""Physical behaviour of the engine in float32 (the default precision), forward only."""
import math

import numpy as np
import pytest

from codesign_mpm import BodySpec, MaterialSpec, MuscleSpec, Scene, ShapeSpec, TerrainSpec, build_particles
from codesign_mpm.engine import SimulationError, Simulator

DX = 1 / 32


def com(sim) -> np.ndarray:
    p = sim.particles
    m = p.volume * p.density
    return (m[:, None] * sim.particles_state()[0]).sum(0) / m.sum()


def incline_scene(theta_deg: float, friction: float, contact: str = "nodes", **options) -> Scene:
    """A stiff block lying flush on a terrain incline that rises along +x: its face an eighth of a cell
    above the surface for the node and spring contacts, its lowest row of particles (a quarter cell
    inside the face at 8 per cell) on the surface for the surface contact, which holds the particles
    there. `options`: more Scene keys (cfl, flip, pic_time)."""
    theta, h0, xc, half = math.radians(theta_deg), 0.1, 0.6, 0.04
    normal = np.array([-math.sin(theta), math.cos(theta), 0.0])
    lift = {"nodes": DX / 8, "surface": -DX / 4, "spring": DX / 8}[contact]
    center = np.array([xc, h0 + math.tan(theta) * xc, 0.25]) + normal * (half + lift)
    return Scene(size=[1.0, 1.0, 0.5], dx=DX, **options,
                 terrain=TerrainSpec(kind="incline", height=h0, slope_deg=theta_deg, friction=friction, contact=contact),
                 bodies=[BodySpec(shape=ShapeSpec(size=[0.16, 0.08, 0.08]), center=center.tolist(),
                                  rotation=[0.0, 0.0, theta_deg], material=MaterialSpec(youngs_modulus=1e5))])


def downhill_travel(scene: Scene, frames: int) -> np.ndarray:
    """How far down the incline of `scene` its block's centre of mass has moved after each frame."""
    theta = math.radians(scene.terrain.slope_deg)
    downhill = np.array([-math.cos(theta), -math.sin(theta), 0.0])
    sim = Simulator(scene, build_particles(scene))
    try:
        start, travel = com(sim), []
        for _ in range(frames):
            sim.step()
            travel.append((com(sim) - start) @ downhill)
        return np.array(travel)
    finally:
        sim.close()


@pytest.mark.parametrize("contact", ["nodes", "surface"])
@pytest.mark.parametrize("theta_deg", [20.0, 35.0])
def test_block_on_incline_slides_iff_tan_theta_exceeds_mu(theta_deg, contact):
    mu, g = 0.5, 3.8
    scene = incline_scene(theta_deg, mu, contact)
    theta = math.radians(theta_deg)
    travel = downhill_travel(scene, 60)
    if math.tan(theta) <= mu:
        # after settling into contact (< a quarter cell, by frame 20) the block does not move at all
        assert abs(travel[0]) < DX / 4
        assert abs(travel[-1] - travel[19]) < 1e-3 * DX
    else:
        t = np.arange(1, 61) * scene.frame_dt
        accel = 2 * np.polyfit(t[20:], travel[20:], 2)[0]
        expected = g * (math.sin(theta) - mu * math.cos(theta))
        assert accel == pytest.approx(expected, rel=0.08)


def gait_distance(cfl: float = 0.4, dx: float = DX, **options) -> float:
    """Distance along x after 1 s of docs/accuracy.md's travelling gait on robot_ground (`options`:
    robot_env's, e.g. flip, terrain_height, contact)."""
    from codesign_mpm.reports.accuracy import Setting
    from codesign_mpm.reports.accuracy import gait_distance as distance

    return distance(Setting(dx=dx, cfl=cfl), **options)


def test_the_surface_contact_does_not_see_where_the_surface_falls_within_a_cell():
    """The node contact holds the layers of nodes below the surface, so moving the terrain by less than
    a cell moved a gait's distance by 16% at dx 1/32 (26.1 and 22.3 mm at offsets 0.05 and 0.75;
    docs/log/contact.md section 13); the surface contact holds the particles at the exact surface
    (measured: 28.4 and 28.5 mm, and 28.0 to 28.5 over four offsets; section 15)."""
    near, far = (gait_distance(terrain_height=(4 + offset) * DX, contact="surface") for offset in (0.05, 0.75))
    assert near > 0.015 and far > 0.015, "the gait should move the box forwards"
    assert near == pytest.approx(far, rel=0.05)


def test_the_surface_contact_converges_in_time():
    """The same gait at dx 1/48 (docs/log/contact.md section 15): 18.6 and 18.4 mm at cfl 0.1 and 0.025.
    The surface contact before (a particle impulse before p2g plus nodes held by their share after
    it) went 21.6 -> 28.5 mm over the same steps, and on to 31.0 at cfl 0.0125."""
    coarse, fine = (gait_distance(cfl, dx=1 / 48, contact="surface") for cfl in (0.1, 0.025))
    assert coarse > 0.01, "the gait should move the box forwards"
    assert fine == pytest.approx(coarse, rel=0.05)


def test_elastic_ball_bounces_and_stays_in_one_piece():
    scene = Scene(size=[1.0, 1.0, 0.5], dx=DX, terrain=TerrainSpec(height=0.1, friction=0.5),
                  bodies=[BodySpec(shape=ShapeSpec(kind="sphere", radius=0.07), center=[0.5, 0.45, 0.25])])
    sim = Simulator(scene, build_particles(scene))
    try:
        p = sim.particles
        m = p.volume * p.density
        vy, extent = [], []
        for _ in range(100):
            sim.step()
            x, v, _, F = sim.particles_state()
            vy.append((m * v[:, 1]).sum() / m.sum())
            extent.append((x.max(0) - x.min(0)).max())
        vy = np.array(vy)
        impact = int(np.argmin(vy))
        assert vy[impact] < -1.0
        assert vy[impact:].max() > 0.5 * -vy[impact], "it should rebound with at least half the impact speed"
        assert max(extent) < 1.15 * 0.14, "it should stay one piece (diameter 0.14)"
        J = np.linalg.det(F)
        assert 0.9 < J.min() and J.max() < 1.1
    finally:
        sim.close()


def robot_scene(**material) -> Scene:
    return Scene(size=[1.0, 0.5, 0.5], dx=DX, terrain=TerrainSpec(height=0.1, friction=0.5),
                 bodies=[BodySpec(robot=True, shape=ShapeSpec(size=[0.16, 0.08, 0.08]), center=[0.5, 0.0, 0.25],
                                  rest_on_terrain=True, material=MaterialSpec(**material),
                                  muscles=MuscleSpec(groups=[2, 2, 1]))])


def gait(frame: int, amplitude: float = 0.3, hz: float = 3.0) -> np.ndarray:
    phase = 2 * math.pi * hz * frame * 8e-3
    return amplitude * np.array([math.sin(phase), math.cos(phase), -math.sin(phase), -math.cos(phase)])


@pytest.fixture(scope="module")
def robot():
    scene = robot_scene()
    sim = Simulator(scene, build_particles(scene))
    yield sim
    sim.close()


def mean_speed_after_settling(sim, action) -> float:
    """Mean particle speed over 40 frames, after 100 frames of settling onto the ground."""
    sim.reset()
    sim.step(np.zeros(4), frames=100)
    speeds = []
    for f in range(40):
        sim.step(action(f))
        speeds.append(np.linalg.norm(sim.particles_state()[1], axis=1).mean())
    return float(np.mean(speeds))


def test_muscles_move_the_robot_only_when_actuated(robot):
    still = mean_speed_after_settling(robot, lambda f: np.zeros(4))
    moving = mean_speed_after_settling(robot, gait)
    assert still < 0.02  # the settling has (nearly) rung down: APIC damps little (measured 0.012)
    assert moving > 0.04  # muscles at 0.3 E: measured 0.046, 3.9 times the residual ringing
    assert moving > 3 * still


def test_full_actuation_over_a_long_horizon_stays_finite(robot):
    robot.reset()
    for f in range(300):
        robot.step(np.sign(gait(f)) * 0.3)  # square wave at the action bound
    x, v, _, F = robot.particles_state()
    J = np.linalg.det(F)
    assert np.isfinite(x).all() and 0.3 < J.min() and J.max() < 3.0
    assert x[:, 1].min() > 0.1 - DX


def test_time_step_above_the_stable_one_blows_up_with_a_clear_error():
    scene = robot_scene(youngs_modulus=1e6)
    scene.dt, scene.allow_unstable_dt = 8e-3 / 2, True  # about 15x the CFL bound
    sim = Simulator(scene, build_particles(scene))
    try:
        with pytest.raises(SimulationError, match=r"at frame \d+"):
            sim.step(np.zeros(4), frames=50)
    finally:
        sim.close()


@pytest.mark.parametrize("model", ["corotated", "stvk"])
def test_other_elastic_models_hold_a_resting_body(model):
    scene = robot_scene(kind=model)
    scene.bodies[0].muscles = None
    sim = Simulator(scene, build_particles(scene))
    try:
        assert sim.layout.models == (1 if model == "corotated" else 2,)
        sim.step(frames=60)
        x, v, _, F = sim.particles_state()
        # it neither collapses nor swells: height within 5%, volume within 2%
        assert x[:, 1].max() - x[:, 1].min() == pytest.approx(0.08 - DX / 2, rel=0.05)
        assert abs(np.linalg.det(F).mean() - 1) < 0.02
    finally:
        sim.close()


def test_elastic_bar_rings_at_its_analytic_frequency_and_converges():
    """f = sqrt(E / rho) / (2 L) for a free-free bar with Poisson's ratio 0. The error is not
    monotone in dx (where the bar's ends fall between nodes matters), so the test bounds it by
    a line in dx at every resolution and compares the envelopes of coarse and fine grids."""
    from codesign_mpm.reports.accuracy import Setting, measure

    errors = {n: measure(Setting(dx=1 / n))["relative_error"] for n in (20, 24, 32, 48, 64)}
    for n, error in errors.items():
        assert error < 0.8 / n, (n, errors)  # measured: 1.5%, 0.0%, 2.1%, 0.8%, 0.2%
    assert max(errors[48], errors[64]) < 0.5 * max(errors[20], errors[24], errors[32]), errors


def test_a_gait_converges_in_time_with_the_flip_share_and_drifts_without_it():
    """APIC damps non-affine motion once per substep, so a gait on terrain loses distance as the
    step shrinks; with the FLIP share it has a limit (docs/log/contact.md section 10). The travelling
    gait for 1 s at dx 1/32: APIC 26.2 mm at cfl 0.4 and 16.0 at cfl 0.1; flip 0.99 29.1 and 28.9."""
    flip = {cfl: gait_distance(cfl, flip=0.99) for cfl in (0.4, 0.1)}
    apic = {cfl: gait_distance(cfl, flip=0.0) for cfl in (0.4, 0.1)}
    assert flip[0.1] == pytest.approx(flip[0.4], rel=0.05)
    assert apic[0.1] < 0.8 * apic[0.4]
