"""Exactness and gradients of the MPM engine in float64.

All differentiable checks share one simulator layout (one compile of the backward kernels,
about two minutes cold, a second once Taichi's offline cache is warm).
"""
from dataclasses import replace

import numpy as np
import pytest

from codesign_mpm import BodySpec, MaterialSpec, MuscleSpec, Scene, ShapeSpec, TerrainSpec, build_particles
from codesign_mpm.engine import SimulationError, Simulator

T = 6  # frames per differentiable rollout
MAX_FRAMES = 12


def robot_scene(**material) -> Scene:
    """A 4-muscle box robot resting on frictional ground: gradients go through contact."""
    return Scene(
        size=[1.0, 0.5, 0.5], dx=1 / 32, dtype="float64",
        terrain=TerrainSpec(kind="flat", height=0.1, friction=0.5),
        bodies=[BodySpec(name="robot", robot=True, shape=ShapeSpec(size=[0.16, 0.08, 0.08]),
                         center=[0.5, 0.0, 0.25], rest_on_terrain=True,
                         material=MaterialSpec(**material), muscles=MuscleSpec(groups=[2, 2, 1]))])


@pytest.fixture(scope="module")
def sim():
    scene = robot_scene()
    s = Simulator(scene, build_particles(scene), requires_grad=True, max_frames=MAX_FRAMES, checkpoint_every=64)
    assert T * s.timestep.substeps <= s.segment, "the plain (one-segment) rollout must fit"
    yield s
    s.close()


@pytest.fixture(scope="module")
def weights():
    rng = np.random.default_rng(7)
    return {"com_x": rng.normal(size=(T + 1, 3)), "com_v": rng.normal(size=(T + 1, 3))}


@pytest.fixture(scope="module")
def actions():
    return np.random.default_rng(3).uniform(-0.3, 0.3, size=(T, 4))


def loss(sim, actions, weights, wx, checkpoint_every=None) -> float:
    out = sim.rollout(actions, checkpoint_every=checkpoint_every)
    return float((weights["com_x"] * out.com_x).sum() + (weights["com_v"] * out.com_v).sum()
                 + (wx * out.x).sum())


def gradients(sim, actions, weights, wx, checkpoint_every=None):
    loss(sim, actions, weights, wx, checkpoint_every)
    return sim.backward(com_x=weights["com_x"], com_v=weights["com_v"], x=wx)


def central_difference(f, eps):
    return (f(eps) - f(-eps)) / (2 * eps)


def test_gradients_match_finite_differences_through_contact_and_checkpoints(sim, actions, weights):
    p = sim.particles
    n = p.n
    wx = np.random.default_rng(11).normal(size=(n, 3)) / n
    base = {k: getattr(p, k).copy() for k in ("volume", "youngs_modulus", "muscle", "v")}
    g = gradients(sim, actions, weights, wx, checkpoint_every=5)
    contact = int(np.argmin(p.x[:, 1]))  # a particle in the bottom layer, touching the ground

    def restore():
        sim.set_design(volume=base["volume"], youngs_modulus=base["youngs_modulus"], muscle=base["muscle"])
        sim.set_initial_state(v=base["v"])

    def perturbed(kind, index, eps):
        restore()
        if kind == "action":
            a = actions.copy()
            a[index] += eps
            return loss(sim, a, weights, wx, 5)
        if kind == "v0":
            v = base["v"].copy()
            v[index] += eps
            sim.set_initial_state(v=v)
        else:
            field = {"stiffness": "youngs_modulus", "muscle": "muscle", "volume": "volume"}[kind]
            value = base[field].copy()
            value[index] += eps
            sim.set_design(**{field: value})
        return loss(sim, actions, weights, wx, 5)

    cases = [
        ("action", (1, 0), 1e-6, g.actions[1, 0]),
        ("action", (4, 3), 1e-6, g.actions[4, 3]),
        ("v0", (contact, 0), 1e-6, g.v0[contact, 0]),
        ("v0", (5, 1), 1e-6, g.v0[5, 1]),
        ("stiffness", contact, 1e-2, g.youngs_modulus[contact]),
        ("muscle", (contact, 2), 1e-6, g.muscle[contact, 2]),
        ("volume", 9, base["volume"][9] * 1e-5, g.volume[9]),
    ]
    try:
        for kind, index, eps, analytic in cases:
            numeric = central_difference(lambda e: perturbed(kind, index, e), eps)
            assert analytic == pytest.approx(numeric, rel=1e-4, abs=1e-9 * max(1.0, abs(numeric))), (kind, index)
    finally:
        restore()


def test_checkpointed_gradients_equal_plain_ones(sim, actions, weights):
    wx = np.zeros((sim.n, 3))
    plain = gradients(sim, actions, weights, wx)  # one segment: every substep stored
    assert sim.recomputed_substeps == 0
    for every in (1, 5, 13):
        ckpt = gradients(sim, actions, weights, wx, checkpoint_every=every)
        # segments end with the episode, so backward recomputes all but the last whole one
        assert sim.recomputed_substeps == sum(sim.frame_substeps[-T:]) - every
        for name in ("actions", "youngs_modulus", "muscle", "volume", "x0", "v0"):
            np.testing.assert_allclose(getattr(ckpt, name), getattr(plain, name), rtol=1e-9,
                                       atol=1e-12 * np.abs(getattr(plain, name)).max(), err_msg=name)


def test_backward_repeats_exactly_after_reusing_the_last_segment(sim, actions, weights):
    """The first backward pass takes the last segment's states from the rollout; a second one
    recomputes them from their checkpoint: both must give the same gradients."""
    wx = np.random.default_rng(5).normal(size=(sim.n, 3)) / sim.n
    first = gradients(sim, actions, weights, wx, checkpoint_every=5)
    second = sim.backward(com_x=weights["com_x"], com_v=weights["com_v"], x=wx)
    for name in ("actions", "youngs_modulus", "muscle", "volume", "x0", "v0"):
        np.testing.assert_array_equal(getattr(second, name), getattr(first, name), err_msg=name)


def test_after_a_backward_pass_the_simulator_continues_from_the_rollouts_end(sim, actions, weights):
    """backward() recomputes earlier segments in the slots; step(), particles_state() and stress() must
    still see the rollout's final state."""
    wx = np.zeros((sim.n, 3))
    out = sim.rollout(actions, checkpoint_every=5)  # several segments
    sim.step(actions[-1], frames=2)
    expected = sim.particles_state()
    gradients(sim, actions, weights, wx, checkpoint_every=5)
    for a, b in zip(sim.particles_state(), (out.x, out.v, out.final.C, out.final.F)):
        np.testing.assert_array_equal(a, b)
    sim.step(actions[-1], frames=2)
    for a, b in zip(sim.particles_state(), expected):
        np.testing.assert_array_equal(a, b)


def test_frames_take_the_substeps_their_state_needs_and_backward_replays_them(sim, actions, weights):
    """A body released stretched to 2.6 times its length along x is stiffer (the neo-Hookean tangent grows
    with F F^T) and fast as it springs back: as it rings, some frames need more substeps than at rest
    and others not. Gradients through those frames match central differences (eps too small to change
    the plan)."""
    F0 = np.tile(np.diag([2.6, 1.0, 1.0]), (sim.n, 1, 1))
    wx = np.random.default_rng(2).normal(size=(sim.n, 3)) / sim.n
    direction = np.random.default_rng(4).normal(size=actions.shape)
    try:
        sim.set_initial_state(F=F0)
        g = gradients(sim, actions, weights, wx, checkpoint_every=5)
        plan = list(sim.frame_substeps)
        assert min(plan) >= sim.timestep.substeps and len(set(plan)) > 1, plan

        def perturbed(eps):
            value = loss(sim, actions + eps * direction, weights, wx)
            assert sim.frame_substeps == plan
            return value

        numeric = central_difference(perturbed, 1e-6)
        assert float((g.actions * direction).sum()) == pytest.approx(numeric, rel=1e-5)
    finally:
        sim.set_initial_state()


def test_gradients_are_the_same_with_the_grids_kept_or_recomputed(sim, actions, weights, monkeypatch):
    """The reverse pass takes each substep's grid from the segment's recompute when it fits the store
    (GRID_STORE_BYTES), else recomputes it: both give the same gradients."""
    from codesign_mpm.engine import simulator as engine  # where the simulator reads these limits

    wx = np.random.default_rng(4).normal(size=(sim.n, 3)) / sim.n
    kept = gradients(sim, actions, weights, wx, checkpoint_every=5)
    assert (sim._grid_boxes.to_numpy()[:5, 6] == 1).all(), "every substep's grid should have been kept"
    monkeypatch.setattr(engine, "GRID_STORE_BYTES", 0)
    recomputed = gradients(sim, actions, weights, wx, checkpoint_every=5)
    assert (sim._grid_boxes.to_numpy()[:5, 6] == 0).all(), "no grid fits an empty store"
    for name in ("actions", "youngs_modulus", "muscle", "volume", "x0", "v0"):
        np.testing.assert_allclose(getattr(recomputed, name), getattr(kept, name), rtol=1e-12,
                                   atol=1e-15 * np.abs(getattr(kept, name)).max(), err_msg=name)


def test_grid_records_grow_to_the_largest_box_a_backward_pass_saw(sim, actions, weights, monkeypatch):
    """Records sized under the particles' box keep nothing; the next rollout's hold every box."""
    from codesign_mpm.engine import simulator as engine  # where the simulator reads these limits

    wx = np.zeros((sim.n, 3))
    monkeypatch.setattr(engine, "GRID_STORE_MARGIN", 0.1)  # records far under any box
    monkeypatch.setattr(sim, "_largest_box", 0)
    gradients(sim, actions, weights, wx, checkpoint_every=5)
    assert (sim._grid_boxes.to_numpy()[:5, 6] == 0).all()
    gradients(sim, actions, weights, wx, checkpoint_every=5)
    assert (sim._grid_boxes.to_numpy()[:5, 6] == 1).all()


def test_gradients_are_the_same_with_checkpoints_in_a_file(sim, actions, weights, monkeypatch):
    """Checkpoints past CHECKPOINT_MEMORY_BYTES go to a temporary file and come back bit for bit."""
    from codesign_mpm.engine import simulator as engine  # where the simulator reads these limits

    wx = np.random.default_rng(5).normal(size=(sim.n, 3)) / sim.n
    in_memory = gradients(sim, actions, weights, wx, checkpoint_every=3)
    assert len(sim._checkpoints) > 2 and sim._checkpoints.spilled == 0
    monkeypatch.setattr(engine, "CHECKPOINT_MEMORY_BYTES", 0)
    in_file = gradients(sim, actions, weights, wx, checkpoint_every=3)
    assert sim._checkpoints.spilled == len(sim._checkpoints), "an empty budget should put every checkpoint in the file"
    for name in ("actions", "youngs_modulus", "muscle", "volume", "x0", "v0"):
        np.testing.assert_array_equal(getattr(in_file, name), getattr(in_memory, name), err_msg=name)


def test_the_private_scatter_equals_the_atomic_one(sim, actions, weights, monkeypatch):
    """p2g's private grid per thread and g2p's adjoint's sum what atomic adds into the shared grid
    sum (the GPU's scatter): the same states and gradients, up to the order of the sums."""
    wx = np.random.default_rng(2).normal(size=(sim.n, 3)) / sim.n
    out = {}
    for copies in ("1", "2"):
        monkeypatch.setenv("CODESIGN_SCATTER_COPIES", copies)
        other = Simulator(sim.scene, sim.particles, requires_grad=True, max_frames=MAX_FRAMES, checkpoint_every=64)
        assert other.layout.scatter_copies == int(copies)
        try:
            final = other.rollout(actions)
            out[copies] = (final, other.backward(com_x=weights["com_x"], com_v=weights["com_v"], x=wx))
        finally:
            other.close()
    (atomic, g_atomic), (private, g_private) = out["1"], out["2"]
    for name in ("x", "v", "C", "F"):
        np.testing.assert_allclose(getattr(private.final, name), getattr(atomic.final, name), rtol=0, atol=1e-12)
    for name in ("actions", "youngs_modulus", "muscle", "volume", "x0", "v0"):
        a, b = getattr(g_atomic, name), getattr(g_private, name)
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-12 * np.abs(a).max(), err_msg=name)


def _outcome_with(variable, value, sim, actions, weights, wx, monkeypatch):
    """A simulator of `sim`'s scene built with the environment `variable` at `value`: its rollout,
    gradients, the state after two frames of `step` (the one-launch forward substep), the
    particles' box, the guard's maxima, and what the guard reports for two broken particles."""
    monkeypatch.setenv(variable, value)
    other = Simulator(sim.scene, sim.particles, requires_grad=True, max_frames=MAX_FRAMES, checkpoint_every=64)
    try:
        final = other.rollout(actions)
        grads = other.backward(com_x=weights["com_x"], com_v=weights["com_v"], x=wx)
        other.step(actions[0], frames=2)
        other.k._bounds(0, other.n)
        box = [other.k.lo[d][None] for d in range(3)] + [other.k.hi[d][None] for d in range(3)]
        guard = (other.k.max_speed[None], other.k.max_wave[None])
        state = other.particles_state()
        broken = [np.ascontiguousarray(a) for a in state]
        broken[0][[7, 9]] = np.nan
        other.k._load_state(0, other.n, *broken)
        other.k._check(0, other.n)
        reported = (other.k.n_bad[None], other.k.first_bad[None])
        return other.layout, (final, grads, state, box, guard, reported)
    finally:
        other.close()


def _assert_same(a, b, gradient_rtol=0.0):
    """States, probes, box and guard bit for bit; gradients within `gradient_rtol` of each array's
    largest magnitude."""
    final_a, grads_a, state_a, box_a, guard_a, reported_a = a
    final_b, grads_b, state_b, box_b, guard_b, reported_b = b
    assert box_a == box_b and guard_a == guard_b
    assert reported_a == reported_b == (2, 7)
    for name in ("x", "v", "C", "F"):
        np.testing.assert_array_equal(getattr(final_a.final, name), getattr(final_b.final, name), err_msg=name)
    np.testing.assert_array_equal(final_a.com_x, final_b.com_x)
    np.testing.assert_array_equal(final_a.com_v, final_b.com_v)
    for x, y in zip(state_a, state_b):
        np.testing.assert_array_equal(x, y)
    for name in ("actions", "youngs_modulus", "muscle", "volume", "x0", "v0"):
        x, y = getattr(grads_a, name), getattr(grads_b, name)
        np.testing.assert_allclose(x, y, rtol=0, atol=gradient_rtol * np.abs(y).max(), err_msg=name)


def test_folded_reductions_give_the_same_box_guard_states_and_gradients(sim, actions, weights, monkeypatch):
    """The GPU's reductions (each of runtime.FOLD_THREADS threads folds its particles, then one
    atomic) find the same particle box and guard values as one atomic per particle: min, max and
    counts do not depend on their order, so states and gradients are bit for bit the same, and the
    guard counts broken particles and names the first alike."""
    wx = np.random.default_rng(3).normal(size=(sim.n, 3)) / sim.n
    unfolded_layout, unfolded = _outcome_with("CODESIGN_FOLD_REDUCTIONS", "0", sim, actions, weights, wx, monkeypatch)
    folded_layout, folded = _outcome_with("CODESIGN_FOLD_REDUCTIONS", "1", sim, actions, weights, wx, monkeypatch)
    assert (unfolded_layout.folded, folded_layout.folded) == (False, True)
    _assert_same(folded, unfolded)


def test_serial_loops_give_the_parallel_loops_states_bit_for_bit_and_gradients_to_round_off(sim, actions, weights, monkeypatch):
    """A storage whose loops run on the launching thread (runtime.serial_loops: a small scene on a
    CPU) does each particle's and node's arithmetic as the thread pool does, p2g's private grids
    keeping their chunks: the same states, probes and guard, bit for bit. The gradients agree to
    round-off: a serial loop is compiled into its kernel's function, where fast-math may fuse a
    multiply-add the separate function of a parallel loop leaves apart (about 1e-14 here)."""
    wx = np.random.default_rng(4).normal(size=(sim.n, 3)) / sim.n
    parallel_layout, parallel = _outcome_with("CODESIGN_SERIAL_LOOPS", "0", sim, actions, weights, wx, monkeypatch)
    serial_layout, serial = _outcome_with("CODESIGN_SERIAL_LOOPS", "1", sim, actions, weights, wx, monkeypatch)
    assert (parallel_layout.serial, serial_layout.serial) == (False, True)
    assert serial_layout.scatter_copies == parallel_layout.scatter_copies > 1, "the private grids' chunks are compared"
    _assert_same(serial, parallel, gradient_rtol=1e-12)


def test_torch_bridge_passes_gradcheck(sim):
    torch = pytest.importorskip("torch")
    from codesign_mpm.environment.bridge import simulate

    E0 = torch.tensor(sim.particles.youngs_modulus.copy())

    def f(actions, stiffness_scale):
        com_x, com_v, x, v = simulate(sim, actions, youngs_modulus=E0 * stiffness_scale, checkpoint_every=7)
        return com_x[-1, 0] + 0.3 * com_v[2:, 1].sum() + x[:, 1].mean()

    actions = torch.tensor(np.random.default_rng(0).uniform(-0.3, 0.3, (3, 4)), requires_grad=True)
    scale = torch.ones(sim.n, dtype=torch.float64, requires_grad=True)
    try:
        assert torch.autograd.gradcheck(f, (actions, scale), eps=1e-6, atol=1e-7, rtol=1e-4, fast_mode=True)
    finally:
        sim.set_design(youngs_modulus=E0.numpy())


def test_backward_after_the_state_changed_is_refused_and_the_bridge_replays_its_rollout(sim):
    torch = pytest.importorskip("torch")
    from codesign_mpm.environment.bridge import simulate

    actions = np.random.default_rng(1).uniform(-0.3, 0.3, (3, 4))
    sim.rollout(actions)
    sim.step(np.full(4, 0.3))  # overwrites the held action row the backward pass would replay
    with pytest.raises(RuntimeError, match="changed since the last rollout"):
        sim.backward(com_x=np.ones((4, 3)))
    E0 = sim.particles.youngs_modulus.copy()

    def grads(meddle) -> tuple:
        a = torch.tensor(actions, requires_grad=True)
        scale = torch.ones(sim.n, dtype=torch.float64, requires_grad=True)
        com_x = simulate(sim, a, youngs_modulus=torch.tensor(E0) * scale)[0]
        meddle()
        com_x[-1, 0].backward()
        return a.grad.numpy(), scale.grad.numpy()

    try:
        clean = grads(lambda: None)
        meddled = grads(lambda: (sim.step(np.full(4, 0.3)), sim.set_design(youngs_modulus=2 * E0)))
        for c, m in zip(clean, meddled):
            np.testing.assert_allclose(m, c, rtol=1e-12, atol=0)
    finally:
        sim.set_design(youngs_modulus=E0)


def test_a_stiffer_design_through_the_bridge_gets_a_stable_step(sim):
    """set_design recomputes the CFL step; at the soft design's step the stiff one blows up."""
    torch = pytest.importorskip("torch")
    from codesign_mpm.environment.bridge import simulate

    soft_E, soft = sim.particles.youngs_modulus.copy(), sim.timestep
    actions = np.full((MAX_FRAMES, 4), 0.3)
    try:
        com_x = simulate(sim, torch.tensor(actions), youngs_modulus=torch.tensor(100 * soft_E))[0]
        assert sim.timestep.stable_dt == pytest.approx(soft.stable_dt / 10) and torch.isfinite(com_x).all()
    finally:
        sim.set_design(youngs_modulus=soft_E)
    scene = robot_scene(youngs_modulus=100 * soft_E[0])
    scene.dt, scene.allow_unstable_dt = soft.dt, True  # what the simulator did before it recomputed
    stale = Simulator(scene, build_particles(scene))
    try:
        with pytest.raises(SimulationError):
            stale.step(np.full(4, 0.3), frames=MAX_FRAMES)
    finally:
        stale.close()


# --------------------------------------------------------------------------- hard cases, backward
def _finite_rollout(sim, actions, **state):
    if state:
        sim.set_initial_state(**state)
    out = sim.rollout(actions)
    g = sim.backward(com_x=np.ones((len(actions) + 1, 3)), x=np.ones((sim.n, 3)) / sim.n)
    assert np.isfinite(out.x).all() and np.isfinite(out.v).all()
    for name in ("actions", "youngs_modulus", "muscle", "volume", "x0", "v0"):
        assert np.isfinite(getattr(g, name)).all(), name
    return out, g


def test_stiff_body_adapts_time_step_and_stays_finite(sim):
    soft = sim.timestep
    try:
        sim.reset(build_particles(robot_scene(youngs_modulus=1e6)))
        # the wave speed grows about 10x, so the CFL step shrinks about 10x
        assert sim.timestep.stable_dt == pytest.approx(soft.stable_dt / 10)
        assert sim.timestep.dt <= sim.timestep.stable_dt
        _finite_rollout(sim, np.full((4, 4), 0.3))
    finally:
        sim.reset(build_particles(robot_scene()))


def test_fast_impact_stays_finite_and_above_ground(sim):
    scene = robot_scene()
    scene.bodies[0].rest_on_terrain = False
    scene.bodies[0].center = [0.5, 0.25, 0.25]
    scene.bodies[0].velocity = [0.0, -8.0, 0.0]
    try:
        sim.reset(build_particles(scene))
        out, _ = _finite_rollout(sim, np.zeros((MAX_FRAMES, 4)))
        assert out.com_v[0, 1] == pytest.approx(-8.0)
        assert out.com_v[-1, 1] > -1.0  # the impact was absorbed
        assert out.x[:, 1].min() > 0.1 - scene.dx  # nothing tunnelled into the terrain
    finally:
        sim.reset(build_particles(robot_scene()))


def test_full_actuation_long_backward_pass_stays_finite(sim):
    signs = np.where(np.arange(MAX_FRAMES)[:, None] % 4 < 2, 1.0, -1.0) * np.array([1, -1, -1, 1])
    out, g = _finite_rollout(sim, 0.3 * signs)
    assert np.abs(g.actions).max() > 0


def test_crushed_and_inverted_elements_stay_bounded_and_the_inverted_one_unfolds(sim):
    """One particle in seven crushed to J = 1e-3, one inverted (J = -0.05): the backward pass stays
    finite, and over 60 frames nothing blows up (it did before the neo-Hookean energy was
    continued below J_MIN: the inverted particle's compression pushed it further inside out)
    while the inverted element is pulled back towards J = 0."""
    F = np.tile(np.eye(3), (sim.n, 1, 1))
    F[::7] = np.diag([0.1, 0.1, 0.1])  # J = 1e-3
    F[3] = np.diag([-0.05, 1.0, 1.0])  # inverted
    try:
        _finite_rollout(sim, np.zeros((T, 4)), F=F)
        sim.set_initial_state(F=F)
        sim.step(np.zeros(4), frames=60)  # a SimulationError here means a blow-up
        J = np.linalg.det(sim.particles_state()[3])
        assert -0.04 < J[3] < 0.0  # measured: -0.031 after 60 frames
        assert np.abs(J).max() < 3.0  # neighbours stretch to make room, within bounds (measured 1.8)
        assert J[::7].min() > 0  # crushed particles are not turned inside out
    finally:
        sim.set_initial_state(F=np.tile(np.eye(3), (sim.n, 1, 1)))


def test_particles_with_tiny_mass_stay_finite(sim):
    volume = sim.particles.volume.copy()
    tiny = volume.copy()
    tiny[::2] *= 1e-9
    try:
        sim.set_design(volume=tiny)
        _finite_rollout(sim, np.full((T, 4), 0.3))
    finally:
        sim.set_design(volume=volume)


def test_rollout_rejects_a_longer_checkpoint_interval_than_allocated(sim):
    with pytest.raises(ValueError, match="checkpoint_every must be in"):
        sim.rollout(np.zeros((T, 4)), checkpoint_every=sim.segment + 1)


# --------------------------------------------------------------------------- exact forward answers
def floating_scene(gravity) -> Scene:
    return Scene(size=[1.0, 1.0, 1.0], dx=1 / 32, dtype="float64", gravity=gravity,
                 terrain=TerrainSpec(kind="none"),
                 bodies=[BodySpec(shape=ShapeSpec(kind="ellipsoid", size=[0.2, 0.14, 0.1]),
                                  center=[0.5, 0.6, 0.5], velocity=[0.3, 0.1, -0.2])])


@pytest.mark.parametrize("region", ["bbox", "full"])
def test_free_fall_matches_the_exact_discrete_trajectory(region):
    scene = floating_scene([0.0, -3.8, 0.0])
    scene.grid_region = region
    sim = Simulator(scene, build_particles(scene))
    try:
        p = sim.particles
        m = p.volume * p.density
        x0 = (m[:, None] * p.x).sum(0) / m.sum()
        frames = 10
        sim.step(frames=frames)
        x, v, C, F = sim.particles_state()
        n, dt = frames * sim.timestep.substeps, sim.timestep.dt
        g, v0 = np.array(scene.gravity), np.array(scene.bodies[0].velocity)
        # v_k = v0 + k dt g and x_k = x_{k-1} + dt v_k (symplectic Euler on every particle)
        np.testing.assert_allclose(v, np.tile(v0 + n * dt * g, (sim.n, 1)), rtol=0, atol=1e-11)
        com = (m[:, None] * x).sum(0) / m.sum()
        np.testing.assert_allclose(com, x0 + n * dt * v0 + dt * dt * g * n * (n + 1) / 2, rtol=0, atol=1e-11)
        np.testing.assert_allclose(F, np.tile(np.eye(3), (sim.n, 1, 1)), atol=1e-11)
    finally:
        sim.close()


def angular_momentum(x, v, C, m, dx):
    """Particle + affine (APIC) angular momentum, sum m (x cross v + dx^2/4 eps:C^T)."""
    affine = np.stack([C[:, 2, 1] - C[:, 1, 2], C[:, 0, 2] - C[:, 2, 0], C[:, 1, 0] - C[:, 0, 1]], axis=1)
    return (m[:, None] * (np.cross(x, v) + dx * dx / 4 * affine)).sum(0)


@pytest.mark.parametrize("flip", [0.0, 0.99])
def test_momentum_is_conserved_without_gravity_and_walls(flip):
    """APIC (flip 0) conserves linear and angular momentum to round-off. The FLIP share conserves
    linear momentum exactly too (what a particle keeps, v_p - V_p^old, sums to zero over the
    particles), but not angular momentum: sum x_p x m_p (v_p - V_p^old) is not zero once the body
    deforms (0.37% of L over these 15 frames). It is zero for a rigid (affine) motion."""
    scene = replace(floating_scene([0.0, 0.0, 0.0]), flip=flip)
    sim = Simulator(scene, build_particles(scene))
    try:
        p = sim.particles
        m = p.volume * p.density
        spin = np.cross([1.0, 2.0, 0.5], p.x - p.x.mean(0))  # rigid rotation + translation
        sim.set_initial_state(v=p.v + spin)
        x, v, C, _ = sim.particles_state()
        P0, L0 = (m[:, None] * v).sum(0), angular_momentum(x, v, C, m, scene.dx)
        sim.step(frames=15)
        x, v, C, F = sim.particles_state()
        assert np.abs(np.linalg.det(F) - 1).max() > 1e-4, "the body should deform, or the test is trivial"
        np.testing.assert_allclose((m[:, None] * v).sum(0), P0, rtol=0, atol=1e-10 * np.abs(P0).max())  # round-off over ~100 substeps
        np.testing.assert_allclose(angular_momentum(x, v, C, m, scene.dx), L0, rtol=0,
                                   atol=(1e-10 if flip == 0 else 1e-2) * np.abs(L0).max())
    finally:
        sim.close()


def test_non_finite_state_is_reported_with_particle_and_material():
    scene = floating_scene([0.0, -3.8, 0.0])
    sim = Simulator(scene, build_particles(scene))
    try:
        x = sim.particles.x.copy()
        x[17] = np.nan
        sim.set_initial_state(x=x)
        with pytest.raises(SimulationError, match=r"particle 17 of body 'body' \(neo_hookean\)"):
            sim.step()
    finally:
        sim.close()


def test_a_scene_without_actuators_rolls_out_and_differentiates():
    """A passive body (no muscles): gradients with respect to v0 against central differences."""
    scene = floating_scene([0.0, -3.8, 0.0])
    sim = Simulator(scene, build_particles(scene), requires_grad=True, max_frames=4, checkpoint_every=5)
    w = np.random.default_rng(4).normal(size=(sim.n, 3))
    v0 = sim.particles.v.copy()

    def loss(v) -> float:
        sim.set_initial_state(v=v)
        return float((w * sim.rollout(np.zeros((4, 0))).x).sum())

    try:
        loss(v0)
        g = sim.backward(x=w)
        assert g.actions.shape == (4, 0)
        for index in [(0, 0), (sim.n // 2, 1)]:
            def shifted(e):
                v = v0.copy()
                v[index] += e
                return loss(v)
            numeric = (shifted(1e-6) - shifted(-1e-6)) / 2e-6
            assert g.v0[index] == pytest.approx(numeric, rel=1e-4), index
    finally:
        sim.close()


def test_a_corotated_body_is_refused_for_gradients_with_a_clear_error():
    """Taichi's reverse mode cannot differentiate the polar decomposition (it failed inside backward())."""
    from codesign_mpm import SceneError

    scene = robot_scene(kind="corotated")
    with pytest.raises(SceneError, match=r"'corotated' is invalid in a differentiable simulator .* use neo_hookean"):
        Simulator(scene, build_particles(scene), requires_grad=True, max_frames=MAX_FRAMES, checkpoint_every=64)
    Simulator(scene, build_particles(scene)).close()  # forward only: fine


@pytest.mark.slow
@pytest.mark.parametrize("model", ["stvk"])
def test_the_other_elastic_models_gradients_match_finite_differences(model, actions, weights):
    """A StVK body (its stress differentiated by Taichi, the neo-Hookean's by hand): actions,
    stiffness and initial velocity through contact, against central differences."""
    scene = robot_scene(kind=model)
    other = Simulator(scene, build_particles(scene), requires_grad=True, max_frames=MAX_FRAMES, checkpoint_every=64)
    p = other.particles
    wx = np.random.default_rng(12).normal(size=(p.n, 3)) / p.n
    contact = int(np.argmin(p.x[:, 1]))
    try:
        g = gradients(other, actions, weights, wx, checkpoint_every=5)

        def perturbed(kind, index, eps):
            a, E, v = actions.copy(), p.youngs_modulus.copy(), p.v.copy()
            {"action": a, "stiffness": E, "v0": v}[kind][index] += eps
            other.set_design(youngs_modulus=E)
            other.set_initial_state(v=v)
            return loss(other, a, weights, wx, 5)

        for kind, index, eps, analytic in [("action", (1, 0), 1e-6, g.actions[1, 0]),
                                           ("action", (4, 3), 1e-6, g.actions[4, 3]),
                                           ("stiffness", contact, 1e-2, g.youngs_modulus[contact]),
                                           ("v0", (contact, 0), 1e-6, g.v0[contact, 0])]:
            numeric = central_difference(lambda e: perturbed(kind, index, e), eps)
            assert analytic == pytest.approx(numeric, rel=1e-4, abs=1e-9 * max(1.0, abs(numeric))), (model, kind)
    finally:
        other.close()
