"""The body library (codesign.bodies): animals, the fish family and body files, without physics."""

import subprocess
import sys

import numpy as np
import pytest
import trimesh

from codesign.bodies import (ANIMALS, FISH_FAMILY, LIBRARY_BODIES, BodyError, get_body, lattice, library_body,
                             load_body)

GROUPS = {"seal": 4, "caterpillar": 12, "fish": 4, "panda": 4}


@pytest.mark.parametrize("name", LIBRARY_BODIES)
def test_library_bodies_are_canonical_solids_with_unit_fibres(name):
    body = library_body(name)
    lo, hi = body.bounds
    assert (hi - lo).max() == pytest.approx(1.0, abs=0.02) and (hi - lo)[0] == (hi - lo).max()  # heading +x
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=0.02)
    points = body.sample(0.02)
    assert len(points) > 500
    assert (body.sdf(points) <= 0).all() and (body.sdf(lattice(lo - 0.2, lo - 0.05, 0.05)) > 0).all()
    labels = body.labels(points)
    np.testing.assert_allclose(np.linalg.norm(labels.fibers, axis=1), 1.0)
    assert (labels.stiffness > 0).all()
    assert set(np.unique(labels.groups)) == set(range(-1, body.n_groups)) - ({-1} if name == "caterpillar" else set())


def test_animals_have_their_characteristic_muscles():
    assert set(ANIMALS) <= set(LIBRARY_BODIES) and set(FISH_FAMILY) <= set(LIBRARY_BODIES)
    for name, k in GROUPS.items():
        assert library_body(name).n_groups == k, name
    fish = library_body("fish")
    points = fish.sample(0.02)
    labels = fish.labels(points)
    side = np.sign(points[:, 2])
    for left, right in ((0, 1), (2, 3)):  # antagonistic pairs: one flank each, fibres along the body
        assert (side[labels.groups == left] < 0).all() and (side[labels.groups == right] > 0).all()
        assert np.abs(labels.fibers[labels.groups == left][:, 0]).min() > 0.99
    panda = library_body("panda")
    legs = panda.labels(p := panda.sample(0.02))
    trunk = p[legs.groups == -1][:, 1].mean()
    for leg in range(4):  # legs hang below the trunk, fibres along them
        assert p[legs.groups == leg][:, 1].max() < trunk and np.abs(legs.fibers[legs.groups == leg][:, 1]).min() > 0.99
    seal = library_body("seal")
    flippers = seal.labels(p := seal.sample(0.02))
    assert p[flippers.groups == 0][:, 2].max() < 0 < p[flippers.groups == 1][:, 2].min()  # left and right
    assert p[flippers.groups == 2][:, 0].max() < 0 and p[flippers.groups == 3][:, 0].max() < 0  # the tail is behind
    caterpillar = library_body("caterpillar")
    groups = caterpillar.labels(p := caterpillar.sample(0.02)).groups
    centres = [p[groups // 2 == s][:, 0].mean() for s in range(6)]
    assert np.all(np.diff(centres) > 0.1)  # one segment after another, tail to head
    assert p[groups % 2 == 0][:, 2].max() < 0 <= p[groups % 2 == 1][:, 2].min()  # each one's left and right half


def test_fitting_scales_uniformly_into_a_box():
    body = library_body("panda").fitted([0.3, 0.1, 0.3], center=[1.0, 2.0, 3.0])
    lo, hi = body.bounds
    assert (hi - lo)[1] == pytest.approx(0.1) and (hi - lo)[0] < 0.3
    np.testing.assert_allclose((lo + hi) / 2, [1.0, 2.0, 3.0], atol=1e-9)
    p = body.sample(0.005)
    canonical = library_body("panda")
    scale = 0.1 / (canonical.bounds[1] - canonical.bounds[0])[1]
    np.testing.assert_allclose(body.sdf(p), scale * canonical.sdf((p - [1.0, 2.0, 3.0]) / scale), atol=1e-9)


def test_a_watertight_mesh_loads_and_its_inside_matches_the_solid(tmp_path):
    path = tmp_path / "capsule.stl"
    trimesh.creation.capsule(height=2.0, radius=0.5).apply_transform(
        trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0])).export(path)
    body = load_body(path)
    lo, hi = body.bounds
    np.testing.assert_allclose(hi - lo, [1.0, 1 / 3, 1 / 3], atol=0.01)  # 3 long, 1 wide -> longest side 1
    assert body.n_groups == 0 and (body.labels(np.zeros((2, 3))).groups == -1).all()
    points = np.array([[0.0, 0.0, 0.0], [0.45, 0.0, 0.0], [0.0, 0.2, 0.0]])
    np.testing.assert_array_equal(body.contains(points), [True, True, False])
    np.testing.assert_allclose(body.sdf(points[:1]), [-1 / 6], atol=0.01)


def test_point_cloud_and_voxel_bodies(tmp_path):
    grid = lattice(np.zeros(3), np.array([2.0, 1.0, 1.0]), 0.1)
    np.savez(tmp_path / "block.npz", points=grid)
    trimesh.PointCloud(grid).export(tmp_path / "block.ply")
    for name in ("block.npz", "block.ply"):
        body = load_body(tmp_path / name)
        lo, hi = body.bounds
        np.testing.assert_allclose(hi - lo, [1.0, 0.5, 0.5], atol=0.03)
        assert body.contains(np.array([[0.0, 0.0, 0.0]])).all()
        assert not body.contains(np.array([[0.0, 0.3, 0.0]])).any()
    voxels = np.zeros((8, 4, 4), dtype=bool)
    voxels[:, 1:3, 1:3] = True
    np.save(tmp_path / "bar.npy", voxels)
    bar = load_body(tmp_path / "bar.npy")
    np.testing.assert_allclose(bar.bounds[1] - bar.bounds[0], [1.0, 0.5, 0.5])
    assert bar.sdf(np.zeros((1, 3)))[0] < 0 and bar.sdf(np.array([[0.0, 0.2, 0.0]]))[0] > 0
    np.testing.assert_allclose(bar.sdf(np.array([[0.0, 0.125, 0.0]])), [0.0], atol=1e-9)  # on the surface


def test_an_annotated_npz_carries_its_labels(tmp_path):
    points = lattice(np.zeros(3), np.array([2.0, 1.0, 1.0]), 0.25)
    groups = np.where(points[:, 1] < 0.3, -1, (points[:, 0] > 1.0).astype(int))  # bottom row passive
    fibers = np.tile([0.0, 2.0, 0.0], (len(points), 1))
    np.savez(tmp_path / "two.npz", points=points, groups=groups, fibers=fibers, group_names=np.array(["back", "front"]),
             spacing=0.25)
    body = load_body(tmp_path / "two.npz")
    assert body.group_names == ("back", "front")
    labels = body.labels(np.array([[-0.3, 0.1, 0.0], [0.3, 0.1, 0.0], [0.3, -0.2, 0.0]]))
    np.testing.assert_array_equal(labels.groups, [0, 1, -1])
    np.testing.assert_allclose(labels.fibers, np.tile([0.0, 1.0, 0.0], (3, 1)))


def test_bad_body_files_are_refused_with_the_file_and_the_problem(tmp_path):
    open_box = trimesh.creation.box()
    open_box.update_faces(np.arange(len(open_box.faces)) != 0)
    open_box.export(tmp_path / "open.obj")
    with pytest.raises(BodyError, match=r"open\.obj: the mesh is not watertight \(\d+ open edges\)"):
        load_body(tmp_path / "open.obj")
    np.save(tmp_path / "empty.npy", np.zeros((3, 3, 3), dtype=bool))
    with pytest.raises(BodyError, match=r"empty\.npy: no voxel is set"):
        load_body(tmp_path / "empty.npy")
    np.savez(tmp_path / "flat.npz", points=np.c_[np.random.default_rng(0).random((20, 2)), np.zeros(20)])
    with pytest.raises(BodyError, match=r"flat\.npz: the solid has no extent along z"):
        load_body(tmp_path / "flat.npz")
    np.savez(tmp_path / "gaps.npz", points=np.random.default_rng(0).random((4, 3)), groups=np.array([0, 2, 2, -1]))
    with pytest.raises(BodyError, match=r"gaps\.npz: muscle groups must be numbered 0..K-1 without gaps"):
        load_body(tmp_path / "gaps.npz")
    with pytest.raises(BodyError, match=r"missing\.obj: no such file"):
        load_body(tmp_path / "missing.obj")
    (tmp_path / "body.txt").write_text("1 2 3")
    with pytest.raises(BodyError, match=r"unsupported type '\.txt'"):
        load_body(tmp_path / "body.txt")
    with pytest.raises(BodyError, match="unknown body 'walrus'"):
        library_body("walrus")
    assert get_body("seal") is library_body("seal")


def test_the_body_library_imports_nothing_heavy():
    code = ("import sys, codesign.bodies\n"
            "print([m for m in ('trimesh', 'scipy', 'sklearn', 'torch', 'taichi') if m in sys.modules])")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "[]"


def test_signed_distances_are_distances_to_half_a_cell():
    """A ball and a box against their analytic distances, inside and out; no point of a slender fish
    lies deeper than half its thickness (its ellipsoid bound says much deeper)."""
    import trimesh

    from codesign.bodies import MeshBody, Part, PartsBody, ellipsoid

    cell, rng = 0.01, np.random.default_rng(0)
    ball = PartsBody("ball", [Part(ellipsoid([0.0, 0.0, 0.0], [0.2, 0.2, 0.2]))], ())
    points = rng.uniform(-0.3, 0.3, (2000, 3))
    assert np.abs(ball.signed_distance(points, cell) - (np.linalg.norm(points, axis=1) - 0.2)).max() < 0.6 * cell
    box = MeshBody("box", trimesh.creation.box(extents=[0.4, 0.16, 0.16]))
    points = rng.uniform([-0.25, -0.1, -0.1], [0.25, 0.1, 0.1], (2000, 3))
    q = np.abs(points) - [0.2, 0.08, 0.08]
    exact = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(1), 0.0)
    assert np.abs(box.signed_distance(points, cell) - exact).max() < 0.6 * cell
    fish = library_body("fish_slender")
    inside = fish.sample(cell)
    half_thickness = (fish.bounds[1] - fish.bounds[0])[2] / 2  # 0.07: the body is thinnest across z
    assert fish.signed_distance(inside, cell).min() >= -half_thickness - 0.6 * cell  # no point deeper than that
    assert fish.sdf(inside).min() < -1.3 * half_thickness
