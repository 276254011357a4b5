"""Body integrity (codesign_mpm.scene.integrity): pieces that share no grid node, a design's thinnest part,
the resolution filter every design goes through, and what a torn episode gets."""
import numpy as np
import pytest

from codesign_mpm.scene.integrity import IntegrityWatch, pieces, resolved_body, thinnest_cells, torn_fraction
from codesign_mpm.scene.sampling import lattice

DX = 1 / 32
H = DX / 2  # the sampling lattice of 8 particles per cell


def box(lo, hi, spacing=H):
    return lattice(np.asarray(lo, float), np.asarray(hi, float), spacing)


def test_pieces_join_exactly_when_stencils_share_a_node():
    """Base cells floor(x / dx - 1/2) at most 2 apart share a node of their 3x3x3 stencils."""
    a = np.array([[10.5, 10.5, 10.5]]) * DX  # base cell 10
    for gap, joined in ((2, True), (3, False)):
        b = a + [gap * DX, 0, 0]
        assert (len(set(pieces(np.vstack([a, b]), DX))) == 1) == joined, gap


def test_pieces_are_the_components_of_the_shared_node_graph():
    """The voxel labelling against the definition, pair by pair, on random clouds of all densities."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(0)
    for n in (5, 50, 200, 400):
        x = rng.uniform(0.0, 0.4, (n, 3))
        base = np.floor(x / DX - 0.5)
        near = (np.abs(base[:, None, :] - base[None, :, :]) <= 2).all(-1)
        _, expected = connected_components(coo_matrix(near), directed=False)
        labels = pieces(x, DX)
        assert len(set(zip(expected, labels))) == len(set(expected)) == len(set(labels)), n


def test_torn_fraction_is_the_mass_outside_the_largest_piece():
    body = box([0.2, 0.2, 0.2], [0.4, 0.28, 0.28])
    piece = box([0.6, 0.2, 0.2], [0.64, 0.24, 0.24])  # 5 cells away: no shared node
    x = np.vstack([body, piece])
    mass = np.ones(len(x))
    assert torn_fraction(body, np.ones(len(body)), DX) == 0.0
    assert torn_fraction(x, mass, DX) == pytest.approx(len(piece) / len(x))
    mass[:len(body)] = 0.01  # by mass, not by count: the small piece is now the body
    assert torn_fraction(x, mass, DX) == pytest.approx(0.01 * len(body) / (0.01 * len(body) + len(piece)))


@pytest.mark.parametrize("cells", [1, 2, 3])
def test_thinnest_cells_of_a_plate_is_its_thickness(cells):
    plate = box([0.2, 0.2, 0.2], [0.5, 0.2 + cells * DX, 0.5])
    assert thinnest_cells(plate, H, DX) == pytest.approx(cells)


def test_a_curved_body_reads_as_thick_as_it_is():
    """A ball 5 cells across, sampled on the lattice: its surface staircase does not make it thin."""
    grid = box([0.2, 0.2, 0.2], [0.36, 0.36, 0.36])
    ball = grid[np.linalg.norm(grid - 0.28, axis=1) <= 2.5 * DX]
    assert thinnest_cells(ball, H, DX) >= 2.5  # its inscribed cube is 2.9 cells wide; without the tolerance: 0.5
    assert resolved_body(ball, np.ones(len(ball), bool), H, DX).all()


def test_the_resolution_filter_drops_thin_fins_and_loose_blobs_and_keeps_thick_bodies():
    body = box([0.2, 0.2, 0.2], [0.4, 0.28, 0.28])  # 6.4 x 2.56 x 2.56 cells
    fin = box([0.4, 0.2, 0.2], [0.5, 0.2 + DX, 0.28])  # one cell thick, attached
    blob = box([0.6, 0.2, 0.2], [0.7, 0.28, 0.28])  # thick but apart, and smaller
    points = np.vstack([body, fin, blob])
    kept = resolved_body(points, np.ones(len(points), bool), H, DX)
    n_body, n_fin = len(body), len(fin)
    assert kept[:n_body].all() and not kept[n_body + n_fin:].any()
    assert (points[n_body:n_body + n_fin][kept[n_body:n_body + n_fin], 0] < 0.4 + DX / 2).all()  # a stub at most
    assert thinnest_cells(points[kept], H, DX) >= 2
    assert not resolved_body(fin, np.ones(len(fin), bool), H, DX).any()  # nothing thick enough: empty


def test_a_watch_records_the_largest_tear_and_when_it_first_exceeded_the_tolerance():
    body = box([0.2, 0.2, 0.2], [0.4, 0.28, 0.28])
    watch = IntegrityWatch(np.ones(len(body)), DX, tolerance=0.01, thinnest=2.5)
    torn = body.copy()
    torn[:20] += [0.3, 0, 0]
    for x in (body, torn, body):  # a piece flies off in frame 2 and (say) comes back in frame 3
        watch.see(x)
    assert watch.torn == pytest.approx(20 / len(body)) and watch.torn_at == 2
    assert watch.metrics() == {"torn_fraction": watch.torn, "thinnest_cells": 2.5, "torn_at_frame": 2.0}


def ground(**changes):
    from codesign_mpm.environment.config import PRESET_CONFIGS, PRESETS, TerrainConfig
    from codesign_mpm.environment.env import LocomotionEnv

    config = PRESET_CONFIGS["ground"](dx=1 / 48, horizon=150, terrain=TerrainConfig(height=0.1, friction=0.5), **changes)
    return LocomotionEnv(config, PRESETS["ground"])


def test_actuation_at_the_bound_keeps_the_quick_start_body_whole():
    """The quick start's box at the default quality, driven bang-bang at the action bound (neighbouring
    muscles in antiphase) for 150 frames: no numerical fracture. With the old default muscle strength
    (stiffness ratio 1, 0.72 x the shear modulus at the bound) 8% of the mass tore off by frame 124."""
    from codesign_mpm.reports.stability import bang_bang

    env = ground()
    try:
        env.reset()
        act = bang_bang(env.action_dim)
        for t in range(env.horizon):
            result = env.step(act(t))
        metrics = result.info["episode_metrics"]
        assert result.done and metrics["torn_fraction"] == 0.0 and metrics["thinnest_cells"] >= 2
        assert np.isfinite(env.sim.particles_state()[0]).all()
    finally:
        env.close()


def test_muscles_stronger_than_the_material_can_carry_are_refused():
    from codesign.errors import RecipeError
    from codesign_mpm.environment.config import RobotConfig

    with pytest.raises(RecipeError, match=r"environment.robot.muscle_stiffness_ratio: 1.0 is too strong .* "
                                          r"must be <= 0.4167 at poisson_ratio 0.2"):
        ground(robot=RobotConfig(muscle_stiffness_ratio=1.0))


@pytest.mark.parametrize("rule, dropped, penalty", [("penalize", [False] * 4, 100 * 4 * 0.04),
                                                    ("terminate", [False, True, True, True], 0.0),
                                                    ("off", [False] * 4, 0.0)])
def test_a_torn_episode_gets_what_the_recipe_says(rule, dropped, penalty):
    """penalize: penalty x horizon x (torn - tolerance) off the last step; terminate: rewards from the
    frame it tore on are dropped; off: nothing. A whole body gets nothing either way."""
    from codesign_mpm.environment.config import IntegrityConfig

    env = ground(integrity=IntegrityConfig(on_tear=rule))
    env.horizon = 4
    try:
        torn = IntegrityWatch(np.ones(3), DX, 0.01, 2.0, torn=0.05, torn_at=2)
        outcomes = [env.tear_outcome(torn, t) for t in range(1, 5)]
        assert [d for d, _ in outcomes] == dropped
        assert sum(p for _, p in outcomes) == pytest.approx(penalty) and outcomes[-1][1] == pytest.approx(penalty)
        whole = IntegrityWatch(np.ones(3), DX, 0.01, 2.0, torn=0.005)
        assert all(o == (False, 0.0) for o in (env.tear_outcome(whole, t) for t in range(1, 5)))
    finally:
        env.close()


def test_a_design_with_nothing_thick_enough_is_not_played_and_ranks_last():
    from codesign.artifacts import play, rank_last
    from codesign.errors import DesignError
    from codesign.interfaces import DesignFields

    env = ground()
    try:
        base = env.base_particles
        thin = np.zeros(base.n)
        thin[base.x[:, 1] < base.x[:, 1].min() + DX / 2] = 1.0  # only the bottom layer: under one cell thick
        design = DesignFields(thin, base.youngs_modulus, base.muscle, base.fiber)
        with pytest.raises(DesignError, match=r"no part at least 2 grid cells thick \(dx = 0.02083"):
            env.design_particles(design)
        record = play(env, design, controller=None)
        assert not record.played and record.metrics == {"unplayable": 1.0}
        assert rank_last([3.0, record.episode_return, -1.0]) == [3.0, -2.0, -1.0]
    finally:
        env.close()


def _audit(scene, frames, actions=None, **initial):
    """max over the frames (up to a SimulationError) of (mechanical energy gained - muscle work), and
    the largest |muscle work|."""
    from codesign_mpm import build_particles
    from codesign_mpm.engine import SimulationError, Simulator
    from codesign_mpm.reports.stability import energy

    sim = Simulator(scene, build_particles(scene))
    sim.audit_work = True
    try:
        if initial:
            sim.set_initial_state(**initial)
        x, v, _, F = sim.particles_state()
        e0, _ = energy(sim, x, v, F)
        excess, work = -np.inf, 0.0
        for f in range(frames):
            try:
                sim.step(None if actions is None else actions(f))
            except SimulationError:
                break
            x, v, _, F = sim.particles_state()
            excess = max(excess, energy(sim, x, v, F)[0] - e0 - sim.muscle_work)
            work = max(work, abs(sim.muscle_work))
        return excess, work
    finally:
        sim.close()


@pytest.mark.parametrize("where", ["ground", "free", "ground with the FLIP share"])
def test_the_body_never_gains_more_energy_than_its_muscles_put_in(where):
    """Energy audit: kinetic + gravitational + elastic energy gained never exceeds the muscles' work
    (friction, contact and APIC transfers only take energy out), driven bang-bang at the action bound
    for 120 frames; and the same audit flags an integrator that creates energy (a step 3x the CFL
    bound, no muscles), so it can fail."""
    from codesign_mpm import BodySpec, MuscleSpec, Scene, ShapeSpec, TerrainSpec
    from codesign_mpm.reports.stability import bang_bang

    on_ground = where.startswith("ground")
    scene = Scene(size=[1.0, 0.5, 0.5], dx=1 / 32, dtype="float64", flip=0.99 if "FLIP" in where else 0.0,
                  terrain=TerrainSpec(kind="flat", height=0.1, friction=0.5) if on_ground else TerrainSpec(kind="none"),
                  gravity=[0.0, -3.8, 0.0] if on_ground else [0.0, 0.0, 0.0],
                  bodies=[BodySpec(name="robot", robot=True, shape=ShapeSpec(size=[0.16, 0.08, 0.08]),
                                   center=[0.5, 0.0 if on_ground else 0.25, 0.25], rest_on_terrain=on_ground,
                                   muscles=MuscleSpec(groups=[2, 2, 1]))])
    excess, work = _audit(scene, 120, bang_bang(4))
    assert work > 1.0 and excess <= 1e-3 * work, (excess, work)

    scene.bodies[0].muscles = None  # no work put in: any energy gained is the integrator's
    scene.frame_dt = scene.dt = 1.5 * scene.dx / 4.0  # CFL number 1.5 (wave speed 3.3 plus the motion)
    scene.allow_unstable_dt = True
    created, _ = _audit(scene, 20, v=np.random.default_rng(0).normal(0, 0.05, (250, 3)))
    assert created > 1e-3 * work, created


@pytest.mark.parametrize("cfl", [0.4, 0.1])
def test_a_body_crushed_by_a_fast_drop_gains_no_energy_with_the_flip_share(cfl):
    """Dropped onto the ground at 8 units/s, twice its wave speed, the box is crushed to J ~ 0.01.
    Particles that kept their FLIP share there gained energy (in 30 frames +0.05 of the drop's at
    cfl 0.4, +0.8 at 0.1); below engine.transfer.J_FLIP they take APIC's velocity, and nothing is created."""
    from codesign_mpm import BodySpec, MuscleSpec, Scene, ShapeSpec, TerrainSpec

    scene = Scene(size=[1.0, 0.5, 0.5], dx=1 / 32, dtype="float64", cfl=cfl, flip=0.99,
                  terrain=TerrainSpec(kind="flat", height=0.1, friction=0.5),
                  bodies=[BodySpec(name="robot", robot=True, shape=ShapeSpec(size=[0.16, 0.08, 0.08]),
                                   center=[0.5, 0.25, 0.25], rest_on_terrain=False, velocity=[0.0, -8.0, 0.0],
                                   muscles=MuscleSpec(groups=[2, 2, 1]))])
    drop = 0.5 * 8.0 ** 2 * 1e3 * 0.16 * 0.08 * 0.08  # the kinetic energy it lands with
    excess, _ = _audit(scene, 30)
    assert excess <= 1e-3 * drop, excess / drop


def test_the_audited_elastic_energy_is_the_one_the_engine_integrates():
    """The audit's volumetric energy (continued below J_MIN as the engine's stress is) has the
    engine's neo-Hookean stress as its derivative: tau = mu (b - I) + lambda J dE/dJ, on both sides of
    J_MIN (a log(J)^2 audit counted crushed particles' energy up to 20x too high)."""
    from codesign_mpm import BodySpec, Scene, ShapeSpec
    from codesign_mpm.engine import Simulator
    from codesign_mpm.materials import lame
    from codesign_mpm.materials.neo_hookean import J_MIN, volumetric_energy
    from codesign_mpm.scene.sampling import build_particles

    scene = Scene(size=[0.5, 0.5, 0.5], dx=1 / 32, dtype="float64",
                  bodies=[BodySpec(name="block", shape=ShapeSpec(size=[0.0625, 0.0625, 0.0625]), center=[0.25, 0.25, 0.25])])
    sim = Simulator(scene, build_particles(scene))
    try:
        mu, la = lame(sim.particles.youngs_modulus[0], sim.particles.poisson_ratio[0])
        for J in (0.02, 0.5 * J_MIN, 2 * J_MIN, 0.7, 1.3):
            a = J ** (1 / 3)
            sim.set_initial_state(F=np.tile(a * np.eye(3), (sim.n, 1, 1)))
            tau = sim.stress()[0]
            h = 1e-7 * J
            slope = (volumetric_energy(np.array(J + h)) - volumetric_energy(np.array(J - h))) / (2 * h)
            np.testing.assert_allclose(tau, (mu * (a * a - 1) + la * J * slope) * np.eye(3), rtol=1e-6, atol=1e-6 * la)
    finally:
        sim.close()
