"""Bad scenes are refused before simulation, with the key, the value and what is allowed."""
import math

import numpy as np
import pytest

from codesign_mpm import BodySpec, MaterialSpec, Scene, SceneError, ShapeSpec, TerrainSpec, build_particles
from codesign_mpm.engine import time_step, wave_speeds
from codesign_mpm.engine.time_step import distinct_rows
from codesign_mpm.scene.spec import validate_scene


def scene(**body) -> Scene:
    return Scene(dx=1 / 32, bodies=[BodySpec(center=[0.5, 0.4, 0.5], **body)])


@pytest.mark.parametrize("body, pattern", [
    (dict(material=MaterialSpec(kind="rubberish")), r"bodies\[0\]\.material\.kind = 'rubberish'.*neo_hookean"),
    (dict(material=MaterialSpec(youngs_modulus=0.0)), r"bodies\[0\]\.material\.youngs_modulus = 0\.0.*> 0"),
    (dict(material=MaterialSpec(youngs_modulus=-5.0)), r"youngs_modulus = -5\.0"),
    (dict(material=MaterialSpec(density=0.0)), r"bodies\[0\]\.material\.density = 0\.0.*> 0"),
    (dict(material=MaterialSpec(poisson_ratio=0.5)), r"poisson_ratio = 0\.5.*\(-1, 0\.5\)"),
    (dict(shape=ShapeSpec(kind="blob")), r"shape\.kind = 'blob'.*box, sphere"),
    (dict(particles_per_cell=6), r"particles_per_cell = 6.*cube number"),
    (dict(material=MaterialSpec(kind="sand", friction_angle=95.0)),
     r"bodies\[0\]\.material\.friction_angle = 95\.0.*\[0, 80\]"),
    (dict(material=MaterialSpec(kind="sand", cohesion=-1.0)), r"material\.cohesion = -1\.0.*>= 0"),
    (dict(material=MaterialSpec(kind="clay", yield_stress=0.0)), r"material\.yield_stress = 0\.0.*> 0"),
    (dict(material=MaterialSpec(kind="snow", critical_compression=1.5)),
     r"material\.critical_compression = 1\.5.*\(0, 1\)"),
    (dict(material=MaterialSpec(kind="snow", max_hardening=0.5)), r"material\.max_hardening = 0\.5.*\[1, 100\]"),
    (dict(material=MaterialSpec(kind="water", bulk_modulus=-1e5)), r"material\.bulk_modulus = -100000\.0.*> 0"),
    (dict(material=MaterialSpec(kind="mud", viscosity=float("nan"))), r"material\.viscosity = nan.*>= 0"),
    (dict(shape=ShapeSpec(kind="layer", thickness=0.0)), r"shape\.thickness = 0\.0.*> 0"),
])
def test_invalid_bodies_name_key_value_and_allowed(body, pattern):
    with pytest.raises(SceneError, match=pattern):
        validate_scene(scene(**body))


def test_body_outside_the_domain_is_refused():
    s = scene()
    s.bodies[0].center = [0.98, 0.4, 0.5]
    with pytest.raises(SceneError, match=r"bodies\[0\]\.center = \[0\.98, 0\.4, 0\.5\].*outside the domain"):
        build_particles(s)


def test_time_step_above_the_stable_one_is_refused_unless_overridden():
    s = scene()
    particles = build_particles(s)
    stable = time_step(s, particles).stable_dt
    s.dt = 2 * stable
    with pytest.raises(SceneError, match=r"dt = .* the CFL bound for this scene is .*allow_unstable_dt"):
        time_step(s, particles)
    s.allow_unstable_dt = True
    assert time_step(s, particles).dt == pytest.approx(s.frame_dt / math.ceil(s.frame_dt / s.dt))


def test_time_step_divides_the_frame_exactly_and_respects_cfl():
    s = scene(velocity=[0.0, -2.0, 0.0])
    ts = time_step(s, build_particles(s))
    assert ts.substeps * ts.dt == pytest.approx(s.frame_dt, rel=1e-12)
    assert ts.dt <= ts.stable_dt
    # the initial speed enters the bound
    assert ts.stable_dt < time_step(scene(), build_particles(scene())).stable_dt


def test_particle_volume_follows_sampling_density():
    coarse = build_particles(scene(particles_per_cell=1))
    fine = build_particles(scene(particles_per_cell=27))
    # same body (a 0.1 cube), same mass whatever the sampling
    assert coarse.volume.sum() == pytest.approx(1e-3, rel=1e-12)
    assert fine.volume.sum() == pytest.approx(1e-3, rel=1e-12)
    assert fine.volume[0] == pytest.approx(1e-3 / fine.n)
    assert coarse.n < fine.n / 20


@pytest.mark.parametrize("dx", [1 / 24, 1 / 32, 1 / 48, 1 / 64])
def test_a_box_has_its_size_and_centre_at_every_dx(dx):
    """The lattice is fitted to the shape: a plain one snapped the 0.08 height to 0.078 or 0.083."""
    size, center = np.array([0.2, 0.08, 0.06]), np.array([0.5, 0.4, 0.5])
    p = build_particles(Scene(dx=dx, bodies=[BodySpec(shape=ShapeSpec(size=size.tolist()), center=center.tolist())]))
    lo, hi = p.x.min(0), p.x.max(0)
    counts = np.round(size / (dx / 2)).astype(int)  # 8 particles per cell: spacing about dx / 2
    spacing = size / counts
    np.testing.assert_allclose(hi - lo + spacing, size, rtol=1e-9)
    np.testing.assert_allclose((lo + hi) / 2, center, atol=1e-12)
    assert p.n == counts.prod()


def test_a_body_resting_on_terrain_has_its_face_on_the_surface():
    scene = Scene(dx=1 / 48, terrain=TerrainSpec(kind="flat", height=0.13),
                  bodies=[BodySpec(shape=ShapeSpec(size=[0.2, 0.08, 0.08]), center=[0.5, 0.0, 0.5], rest_on_terrain=True)])
    y = build_particles(scene).x[:, 1]
    assert y.min() - (y.max() - y.min()) / (2 * (np.unique(y.round(9)).size - 1)) == pytest.approx(0.13, abs=1e-12)
    assert (y.max() + y.min()) / 2 == pytest.approx(0.13 + 0.04, abs=1e-12)


def test_bad_scene_values():
    with pytest.raises(SceneError, match=r"cfl = 1\.5"):
        validate_scene(Scene(cfl=1.5, bodies=[BodySpec()]))
    with pytest.raises(SceneError, match=r"flip = 1\b.*\[0, 1\)"):
        validate_scene(Scene(flip=1, bodies=[BodySpec()]))
    with pytest.raises(SceneError, match=r"terrain\.kind = 'lava'"):
        validate_scene(Scene(terrain=TerrainSpec(kind="lava"), bodies=[BodySpec()]))
    with pytest.raises(SceneError, match=r"terrain\.contact = 'grid'.*nodes, surface"):
        validate_scene(Scene(terrain=TerrainSpec(contact="grid"), bodies=[BodySpec()]))
    with pytest.raises(SceneError, match=r"bodies = \[\].*at least one body"):
        validate_scene(Scene())
    with pytest.raises(SceneError, match=r"dtype = 'float16'"):
        validate_scene(Scene(dtype="float16", bodies=[BodySpec()]))


def test_shapes_sample_their_volume():
    dx = 1 / 32
    for shape, volume in [(ShapeSpec(kind="sphere", radius=0.1), 4 / 3 * np.pi * 0.1 ** 3),
                          (ShapeSpec(kind="ellipsoid", size=[0.2, 0.1, 0.16]), np.pi / 6 * 0.2 * 0.1 * 0.16),
                          (ShapeSpec(kind="capsule", radius=0.05, length=0.1),
                           np.pi * 0.05 ** 2 * 0.1 + 4 / 3 * np.pi * 0.05 ** 3)]:
        p = build_particles(Scene(dx=dx, bodies=[BodySpec(shape=shape, center=[0.5, 0.5, 0.5], particles_per_cell=27)]))
        assert p.volume.sum() == pytest.approx(volume, rel=1e-12), shape.kind
        cell = [np.diff(np.unique(p.x[:, a].round(12))).min() for a in range(3)]  # about dx / 3 each
        lattice_volume = p.n * np.prod(cell)  # and the lattice really fills the shape
        assert lattice_volume == pytest.approx(volume, rel=0.06), shape.kind


def test_voxel_and_point_cloud_shapes(tmp_path):
    occ = np.zeros((4, 3, 2), dtype=bool)
    occ[:, :2] = True
    np.save(tmp_path / "robot.npy", occ)
    s = Scene(dx=1 / 32, bodies=[BodySpec(shape=ShapeSpec(kind="voxels", file=str(tmp_path / "robot.npy"),
                                                           voxel_size=0.05), center=[0.5, 0.5, 0.5])])
    p = build_particles(s)
    assert p.volume.sum() == pytest.approx(occ.sum() * 0.05 ** 3, rel=1e-12)
    assert p.n * (1 / 64) ** 3 == pytest.approx(occ.sum() * 0.05 ** 3, rel=0.15)
    grid = np.stack(np.meshgrid(*[np.linspace(0, 1, 11)] * 3, indexing="ij"), -1).reshape(-1, 3)
    np.save(tmp_path / "cloud.npy", grid)
    s.bodies[0].shape = ShapeSpec(kind="points", file=str(tmp_path / "cloud.npy"), scale=0.2)
    p = build_particles(s)
    assert p.n == len(grid)
    assert p.volume.sum() == pytest.approx(0.2 ** 3, rel=0.35)
    s.bodies[0].shape.file = str(tmp_path / "missing.npy")
    with pytest.raises(SceneError, match=r"shape\.file = .*missing\.npy.*no such file"):
        build_particles(s)


def test_time_step_accounts_for_water_bulk_modulus_and_snow_hardening():
    """c = sqrt(K / rho) for water; snow at its largest hardening, sqrt(max_hardening) faster."""
    def stable(**material):
        s = scene(material=MaterialSpec(**material))
        return time_step(s, build_particles(s)).stable_dt

    s = scene()
    assert stable(kind="water", bulk_modulus=4e5) == pytest.approx(s.cfl * s.dx / math.sqrt(4e5 / 1e3), rel=1e-12)
    assert stable(kind="snow", max_hardening=9.0) == pytest.approx(stable(kind="neo_hookean") / 3, rel=1e-12)
    # a viscous material also respects the explicit diffusion limit rho dx^2 / (6 eta)
    assert stable(kind="mud", viscosity=1e3) == pytest.approx(s.cfl * 1e3 * s.dx ** 2 / 6e3, rel=1e-12)


def test_each_particle_of_a_body_with_its_own_stiffness_gets_its_own_wave_speed():
    """The CFL table groups particles by material (`distinct_rows`, numpy's unique without its slow
    record sort): a body whose every particle has its own E, as the particle representation
    makes, must still give each particle sqrt((lambda + 2 mu) / rho) of its own E."""
    s = scene(material=MaterialSpec(poisson_ratio=0.3))
    p = build_particles(s)
    rng = np.random.default_rng(0)
    p.youngs_modulus = rng.choice([1e4, 3e4, 1e5], p.n) * rng.choice([1.0, 1.5], p.n)  # 6 kinds, repeated
    speeds, _ = wave_speeds(s, p)
    nu = 0.3
    p_modulus = p.youngs_modulus * (1 - nu) / ((1 + nu) * (1 - 2 * nu))  # lambda + 2 mu
    np.testing.assert_allclose(speeds, np.sqrt(p_modulus / p.density), rtol=1e-12)
    table = np.column_stack([rng.integers(0, 3, 500), rng.choice([0.0, -1.5, 2.0], (500, 3))])
    kinds, of_row = distinct_rows(table)
    expected_kinds, expected_of_row = np.unique(table, axis=0, return_inverse=True)
    np.testing.assert_array_equal(kinds, expected_kinds)
    np.testing.assert_array_equal(of_row, expected_of_row.ravel())


def test_a_layer_fills_the_terrain_around_other_bodies_without_overlap():
    s = Scene(dx=1 / 32, terrain=TerrainSpec(kind="perlin", height=0.1, amplitude=0.05),
              bodies=[BodySpec(center=[0.5, 0.0, 0.5], rest_on_terrain=True),
                      BodySpec(shape=ShapeSpec(kind="layer", thickness=0.06), material=MaterialSpec(kind="sand"))])
    p = build_particles(s)
    body, layer = p.x[p.body == 0], p.x[p.body == 1]
    assert not inside_particles(layer, body, np.cbrt(p.volume[p.body == 0][0])).any()
    from codesign_mpm.scene.terrain import height_map

    h = height_map(s)
    ij = np.round(layer[:, [0, 2]] / s.dx).astype(int)
    depth = layer[:, 1] - h[ij[:, 0], ij[:, 1]]
    assert depth.min() > 0 and depth.max() < 0.06  # on the terrain, at most the thickness deep
    # 8 per cell: each column spans the layer exactly, whatever the spacing, so a free column holds
    # the thickness's volume (on a plain lattice the layer snapped to whole spacings: 0.0625 here)
    spacing = s.dx / 2
    _, count = np.unique(np.floor(layer[:, [0, 2]] / spacing).astype(int), axis=0, return_counts=True)
    rows = count.max()
    assert (count == rows).mean() > 0.9  # the columns the body leaves whole
    assert np.allclose(p.volume[p.body == 1] * rows, spacing ** 2 * 0.06)
    row = depth / (0.06 / rows) - 0.5  # each particle at the middle of its row above its own ground
    assert np.allclose(row, np.round(row)) and set(np.round(row).astype(int)) == set(range(rows))


def inside_particles(points: np.ndarray, particles: np.ndarray, width: float) -> np.ndarray:
    """Which points lie in the cubes of edge `width` centred on the particles."""
    from scipy.spatial import cKDTree

    distance, _ = cKDTree(particles).query(points, p=np.inf)
    return distance < width / 2


@pytest.mark.parametrize("offset", [0.0, 0.75])
def test_a_layer_tiles_the_space_a_resting_box_leaves(offset):
    """The layer's volume is the thickness over the floor the box leaves free, with no layer
    particle inside the box, wherever the terrain falls within a cell. Cut by grid cells instead,
    the layer left up to a cell free around the box (0.7% of its volume here) and, with the terrain
    0.75 of a cell above a node, laid a sheet of sand inside the box's lowest half row (the robot's
    distance in the desert halved: docs/log/contact.md section 21)."""
    dx, thickness = 1 / 32, 0.03
    s = Scene(dx=dx, terrain=TerrainSpec(height=(4 + offset) * dx),
              bodies=[BodySpec(center=[0.5, 0.0, 0.5], rest_on_terrain=True, shape=ShapeSpec(size=[0.1] * 3)),
                      BodySpec(shape=ShapeSpec(kind="layer", thickness=thickness),
                               material=MaterialSpec(kind="sand"))])
    p = build_particles(s)
    box, layer = p.body == 0, p.body == 1
    assert not inside_particles(p.x[layer], p.x[box], np.cbrt(p.volume[box][0])).any()
    size = np.asarray(s.size)
    free = (size[0] - 2 * s.wall) * (size[2] - 2 * s.wall) - 0.1 * 0.1
    # measured 0.16% over (cut by cells: 0.74% under)
    assert p.volume[layer].sum() == pytest.approx(free * thickness, rel=2e-3)


def test_a_water_slab_placed_flush_with_both_walls_keeps_its_height():
    """Wall to wall, a slab has nowhere to go: with placement and walls agreeing (Scene.wall) it
    keeps its height; when bodies had to start a cell from the wall, a 12-cell slab lost ~17%."""
    from codesign_mpm.engine import Simulator

    dx, cells, height = 1 / 32, 12, 0.1
    scene = Scene(size=[(cells + 4) * dx, 0.3, (cells + 4) * dx], dx=dx, dtype="float64", terrain=TerrainSpec(kind="none"),
                  bodies=[BodySpec(shape=ShapeSpec(size=[cells * dx, height, cells * dx]),
                                   material=MaterialSpec(kind="water", bulk_modulus=1e5))])
    scene.bodies[0].center = [scene.size[0] / 2, scene.wall + height / 2, scene.size[2] / 2]
    assert scene.wall + cells * dx == pytest.approx(scene.size[0] - scene.wall)  # flush on both sides
    sim = Simulator(scene, build_particles(scene))
    try:
        top0 = sim.particles_state()[0][:, 1].max()
        sim.step(frames=40)
        x = sim.particles_state()[0]
        assert x[:, 1].max() - scene.wall > 0.97 * (top0 - scene.wall)  # measured: 1.02 (it rings about its rest height)
    finally:
        sim.close()
