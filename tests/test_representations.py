"""The design representations beyond `particle`: fields, gradients, parameter counts, primitives.

Everything here is torch on a box workspace, no physics (the end-to-end gradient through the
simulator is in tests/mpm/test_designs_env.py).
"""

import numpy as np
import pytest
import torch

from codesign.bodies import get_body, lattice
from codesign.errors import RecipeError
from codesign.geometry import grid_partition
from codesign.interfaces import DesignSpace
from codesign.plugins import get_registry
from codesign.schema import convert
from codesign_designs.primitives import group_centroids, muscle_correspondence, primitive_muscle
from codesign_designs.rotations import (average_rotations, facing, facing_heading, fiber_rotations, principal_axes,
                                       special_procrustes)
from codesign_designs.wasserstein import debiased_barycenter

NEW = ["voxel", "implicit", "diff_cppn", "sdf_lerp", "wasserstein"]
E0 = 2e4
LO, HI = np.zeros(3), np.array([0.2, 0.08, 0.08])


@pytest.fixture(autouse=True)
def small_tensors():
    """float64 (finite differences) and one torch thread: on two shared cores, threads cost more
    than they bring to tensors this small."""
    dtype, threads = torch.get_default_dtype(), torch.get_num_threads()
    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(1)
    yield
    torch.set_default_dtype(dtype)
    torch.set_num_threads(threads)


def box_space(k: int = 4, spacing: float = 0.01, bare: bool = False) -> DesignSpace:
    points = lattice(LO, HI, spacing)
    if bare:
        return DesignSpace(points=points, n_actuators=k, default_stiffness=E0)
    return DesignSpace(points=points, n_actuators=k, default_stiffness=E0, bounds=np.stack([LO, HI]),
                       muscle=np.eye(k)[grid_partition(points, (k, 1, 1))],
                       fiber=np.tile([1.0, 0, 0], (len(points), 1)))


def build(name: str, space: DesignSpace | None = None, seed: int = 0, **config):
    entry = get_registry().get("representation", name)
    representation = entry.load_factory()(entry.load_config()(**config))
    representation.setup(box_space() if space is None else space, np.random.default_rng(seed))
    return representation


def test_every_representation_is_registered_with_a_valid_default_config():
    registry = get_registry()
    for name in ["particle", *NEW]:
        entry = registry.get("representation", name)
        assert entry.description and convert(entry.load_config(), {})[1] == []


@pytest.mark.parametrize("name", NEW)
def test_fields_have_the_design_space_shapes_and_ranges(name):
    space = box_space()
    design = build(name, space)()
    n = len(space.points)
    assert design.occupancy.shape == (n,) and design.stiffness.shape == (n,)
    assert design.muscle.shape == (n, 4) and design.fiber.shape == (n, 3)
    assert 0 <= design.occupancy.min() and design.occupancy.max() <= 1 and (design.occupancy >= 0.5).any()
    assert (design.stiffness > 0).all() and (design.muscle >= 0).all()
    assert (design.muscle.sum(1) <= 1 + 1e-9).all()  # a membership: softmax rows, or passive (zero) rows
    torch.testing.assert_close(design.fiber.norm(dim=1), torch.ones(n))


@pytest.mark.parametrize("name, k", [(name, k) for name in NEW
                                     for k in ((4, 6) if name in ("sdf_lerp", "wasserstein") else (1, 4))])
def test_parameter_counts_are_the_documented_ones(name, k):  # a blend's primitives need >= 4 actuators
    representation = build(name, box_space(k))
    count = sum(t.numel() for t in representation.parameters())
    expected = {"voxel": 8 * 3 * 3 * (2 + k), "implicit": 1378 + 33 * k, "diff_cppn": 1982 + 21 * k,
                "sdf_lerp": 4 * 5, "wasserstein": 4 * 5}[name]
    assert count == expected and all(t.requires_grad for t in representation.parameters())


@pytest.mark.parametrize("name, config", [("voxel", dict(muscle_init="random")), ("implicit", {}), ("diff_cppn", {}),
                                          ("sdf_lerp", dict(init_noise=0.5)), ("wasserstein", dict(init_noise=0.5))])
def test_initialisation_comes_from_the_given_generator(name, config):
    first, again, other = (build(name, seed=s, **config).parameters() for s in (1, 1, 2))
    assert all(torch.equal(a, b) for a, b in zip(first, again))
    assert not all(torch.equal(a, b) for a, b in zip(first, other))


@pytest.mark.parametrize("name, config", [
    ("voxel", {}), ("voxel", dict(interpolation="nearest", muscle_init="random")), ("implicit", {}),
    ("diff_cppn", {}), ("sdf_lerp", dict(init_noise=0.3)), ("wasserstein", dict(init_noise=0.3, resolution=12))])
def test_gradient_of_a_loss_on_the_fields_matches_finite_differences(name, config):
    representation = build(name, box_space(spacing=0.02), **config)
    design = representation()
    rng = np.random.default_rng(3)
    weights = [torch.tensor(rng.normal(size=tuple(t.shape))) for t in (design.occupancy, design.stiffness,
                                                                         design.muscle, design.fiber)]

    def loss() -> torch.Tensor:
        d = representation()
        fields = (d.occupancy, d.stiffness / E0, d.muscle, d.fiber)
        return sum((w * f).sum() for w, f in zip(weights, fields))

    loss().backward()
    for tensor in representation.parameters():
        grad = tensor.grad.reshape(-1)
        for index in {int(grad.abs().argmax()), int(rng.integers(grad.numel()))}:
            flat, eps = tensor.data.reshape(-1), 1e-6
            with torch.no_grad():
                flat[index] += eps
                up = loss().item()
                flat[index] -= 2 * eps
                down = loss().item()
                flat[index] += eps
            assert grad[index].item() == pytest.approx((up - down) / (2 * eps), rel=1e-5, abs=1e-7)


def one_hot(representation, i: int) -> None:
    with torch.no_grad():
        for logits in representation.parameters():
            logits.fill_(-1e4)
            logits[i] = 0.0


@pytest.mark.parametrize("primitive", range(5))
def test_sdf_lerp_with_a_one_hot_weight_is_that_primitive(primitive):
    space = box_space(spacing=0.005)
    representation = build("sdf_lerp", space)
    one_hot(representation, primitive)
    design = representation()
    body = representation.placed[primitive]
    labels = body.labels(space.points)
    inside = body.contains(space.points)
    assert inside.sum() > 200
    np.testing.assert_array_equal(design.occupancy.detach().numpy() > 0.5, inside)
    np.testing.assert_allclose(design.stiffness.detach().numpy(), E0 * labels.stiffness)
    expected = primitive_muscle(labels.groups, representation.actuators[primitive], 4)
    np.testing.assert_allclose(design.muscle.detach().numpy(), expected)
    alignment = (design.fiber.detach().numpy() * labels.fibers).sum(1)  # the same fibre, up to its sign
    np.testing.assert_allclose(np.abs(alignment), 1.0, atol=1e-9)
    lo, hi = body.bounds
    assert lo[1] == pytest.approx(LO[1]) and (lo + hi)[[0, 2]] / 2 == pytest.approx((LO + HI)[[0, 2]] / 2)


@pytest.mark.parametrize("blend", ["sdf_lerp", "wasserstein"])
def test_a_blend_of_annotated_body_files_is_the_blend_of_the_bodies_they_came_from(tmp_path, blend):
    """Two library fish through `codesign annotate` (lattice samples in a file) blend 50/50 into
    the same solid as the library bodies themselves (once 961 particles against 1,487 in
    SDF-Lerp: the files' bodies were 30% too fat and their distances at most a sample deep)."""
    from codesign_designs.annotate import annotate, save_annotation

    names = ["fish_slender", "fish_deep"]
    files = []
    for name in names:
        save_annotation(annotate(get_body(name), groups=4, resolution=48), tmp_path / f"{name}.npz")
        files.append(str(tmp_path / f"{name}.npz"))
    space = box_space(spacing=0.005)
    occupied = []
    for primitives in (names, files):
        representation = build(blend, space, primitives=primitives, init_noise=0.0)  # equal weights
        occupied.append(int((representation().occupancy > 0.5).sum()))
    # the barycenter's blur turns the files' staircase surfaces into a few percent (9% before)
    assert occupied[1] == pytest.approx(occupied[0], rel={"sdf_lerp": 0.03, "wasserstein": 0.07}[blend]), occupied


def rotation_z(degrees: float) -> torch.Tensor:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_procrustes_average_of_rotations():
    r = torch.tensor(fiber_rotations(np.array([[0.3, -0.5, 0.8]])))[0]
    torch.testing.assert_close(special_procrustes(0.3 * r + 0.7 * r), r)  # identical rotations: that rotation
    for w in (0.5, 0.2, 0.9):  # two rotations about z: a rotation about z between them, halfway at w = 1/2
        mean = special_procrustes(w * rotation_z(10.0) + (1 - w) * rotation_z(70.0)).numpy()
        angle = np.degrees(np.arctan2(mean[1, 0], mean[0, 0]))
        chord = np.degrees(np.arctan2(w * np.sin(np.radians(10)) + (1 - w) * np.sin(np.radians(70)),
                                      w * np.cos(np.radians(10)) + (1 - w) * np.cos(np.radians(70))))
        assert 10 < angle < 70 and angle == pytest.approx(chord) and mean[2, 2] == pytest.approx(1.0)
    assert np.degrees(np.arctan2(*special_procrustes(rotation_z(10.0) + rotation_z(70.0)).numpy()[[1, 0], 0])) == \
        pytest.approx(40.0)
    reflection = torch.diag(torch.tensor([1.0, 1.0, -1.0]))  # nearest rotation, never a reflection
    assert torch.linalg.det(special_procrustes(reflection + 0.1 * torch.eye(3))) == pytest.approx(1.0)
    generic = torch.tensor(np.random.default_rng(0).normal(size=(4, 3, 3)), requires_grad=True)
    at_rotation = torch.tensor(fiber_rotations(np.random.default_rng(1).normal(size=(4, 3))), requires_grad=True)
    assert torch.autograd.gradcheck(special_procrustes, (generic,))
    assert torch.autograd.gradcheck(special_procrustes, (at_rotation,))  # repeated singular values


def test_fibres_are_rotations_of_the_heading_that_face_it():
    fibers = np.random.default_rng(2).normal(size=(50, 3))
    rotations = fiber_rotations(fibers)
    np.testing.assert_allclose(rotations @ np.array([1.0, 0, 0]), facing_heading(fibers), atol=1e-12)
    np.testing.assert_allclose(rotations @ np.swapaxes(rotations, 1, 2), np.tile(np.eye(3), (50, 1, 1)), atol=1e-12)
    assert (facing_heading(fibers)[:, 0] >= 0).all()


def test_muscle_groups_correspond_by_place_across_primitives():
    """A second primitive whose groups are the first's, numbered otherwise, drives the same actuators
    with the same parts; a group with no points takes what is left; more groups than actuators is
    a recipe error naming the primitive."""
    points = np.random.default_rng(4).uniform(size=(400, 3))
    quarter = np.minimum((points[:, 0] * 4).astype(int), 3)  # four parts front to back
    renumbered = np.array([2, 0, 3, 1])
    first = group_centroids(points, quarter, 4)
    second = group_centroids(points, renumbered[quarter], 4)
    sparse = group_centroids(points, np.where(quarter == 3, -1, quarter), 5)  # group 3 empty, group 4 never used
    actuators = muscle_correspondence([first, second, sparse], 6)
    np.testing.assert_array_equal(actuators[0], [0, 1, 2, 3])
    np.testing.assert_array_equal(actuators[1][renumbered], [0, 1, 2, 3])  # part q drives actuator q in both
    np.testing.assert_array_equal(actuators[2][:3], [0, 1, 2])
    assert set(actuators[2][3:]) <= {3, 4, 5} and len(set(actuators[2])) == 5  # the empty ones take what is left
    with pytest.raises(RecipeError, match=r"primitives\[0\]: 'caterpillar' has 12 muscle groups, more than the robot's "
                                          r"4 actuators"):
        build("sdf_lerp", primitives=["caterpillar", "fish"])


def test_fibres_either_side_of_the_yz_plane_average_to_their_common_axis():
    """Two leg fibres 2.3 degrees apart across the yz-plane: facing +x they pointed opposite ways and
    averaged to +x; blended about their principal axis they average to y, whatever their signs."""
    half = np.radians(1.15)
    for signs in ([1, 1], [1, -1], [-1, 1]):
        fibers = np.array([[[np.sin(half), np.cos(half), 0.0], [-np.sin(half), np.cos(half), 0.0]]])
        fibers = fibers * np.array(signs)[None, :, None]
        axis = principal_axes(fibers)
        np.testing.assert_allclose(axis, [[0.0, 1.0, 0.0]], atol=1e-12)
        rotations = torch.tensor(fiber_rotations(fibers, axis[:, None, :]))
        for w in (0.5, 0.2):
            blended = average_rotations(rotations, torch.tensor([w, 1 - w]))[0] @ torch.tensor(axis[0])
            angle = np.degrees(np.arctan2(blended[0].item(), blended[1].item()))
            chord = np.degrees(np.arctan2((2 * w - 1) * np.sin(half), np.cos(half)))  # the two rotations' chord
            assert angle == pytest.approx(chord, abs=1e-9)  # between the two, by weight
    fibers = np.random.default_rng(3).normal(size=(20, 3, 3))
    np.testing.assert_allclose(principal_axes(fibers), principal_axes(-fibers), atol=1e-12)
    axes = principal_axes(fibers)[:, None, :]
    np.testing.assert_allclose(fiber_rotations(fibers, axes) @ principal_axes(fibers)[:, None, :, None],
                               facing(fibers, axes)[..., None], atol=1e-12)


@pytest.mark.parametrize("primitive", [0, 1, 4])
def test_wasserstein_with_a_one_hot_weight_is_that_primitive(primitive):
    space = box_space(spacing=0.005)
    representation = build("wasserstein", space)
    one_hot(representation, primitive)
    mass = representation.mass().detach()
    own = representation.occupancy[primitive]
    assert (mass - own).abs().max() < 0.06 and (mass - own).abs().mean() < 0.005
    inside = representation.placed[primitive].contains(space.points)
    agree = (representation().occupancy.detach().numpy() > 0.5) == inside
    assert agree.mean() > 0.97


def test_wasserstein_keeps_total_mass_for_mixed_weights():
    representation = build("wasserstein", box_space(spacing=0.02), resolution=12)
    for seed in range(3):
        weights = torch.softmax(torch.tensor(np.random.default_rng(seed).normal(size=5)), 0)
        assert representation.mass(weights).sum().item() == pytest.approx((weights @ representation.volumes).item())


def test_the_barycenter_moves_mass_continuously_between_primitives():
    """Two boxes of widths 6 and 8 voxels, 12 apart: weighted t, the barycenter is a box of width
    6 + 2t whose centre slides linearly (displacement interpolation), never a fade of the two."""
    shape = (24, 10, 10)
    boxes = np.zeros((2,) + shape)
    boxes[0, 2:8, 2:8, 2:8] = 1
    boxes[1, 14:22, 2:8, 2:8] = 1
    density = (boxes + 1e-12) / (boxes + 1e-12).sum((1, 2, 3), keepdims=True)
    kernels = [torch.tensor(np.exp(-np.subtract.outer(np.arange(n), np.arange(n)) ** 2 / (2 * 0.7 ** 2)))
               for n in shape]

    def barycenter(t: float) -> np.ndarray:
        return debiased_barycenter(torch.tensor(np.log(density)), torch.tensor([1 - t, t]), kernels, 60).numpy()

    ts = np.linspace(0, 1, 11)
    profiles = [barycenter(t).sum((1, 2)) for t in ts]
    centres = [p @ np.arange(24) for p in profiles]
    np.testing.assert_allclose(centres, 4.5 + ts * (17.5 - 4.5), atol=0.05)
    middle = profiles[5] * boxes[0].sum()  # voxels of mass per x slice, halfway
    assert middle[:7].sum() < 0.5 and middle[16:].sum() < 0.5 and middle[8:15].min() > 25  # moved, not faded
    base = barycenter(0.4)
    steps = [np.abs(barycenter(0.4 + dt) - base).sum() for dt in (1e-2, 1e-3)]
    assert 0 < steps[1] < 0.05 and steps[0] / steps[1] == pytest.approx(10, rel=0.2)  # small change, linearly


def test_a_large_barycenter_differentiates_in_checkpointed_segments_with_the_same_gradient(monkeypatch):
    """Past GRAPH_MEMORY_BYTES the Sinkhorn iterations are recomputed segment by segment in the
    backward pass: the graph keeps a fraction of the tensors, and the gradient is the same."""
    from codesign_designs import wasserstein

    rng = np.random.default_rng(5)
    density = rng.uniform(0.1, 1.0, (3, 12, 8, 8))
    log_density = torch.tensor(np.log(density / density.sum((1, 2, 3), keepdims=True)))
    kernels = [torch.tensor(np.exp(-np.subtract.outer(np.arange(n), np.arange(n)) ** 2 / 2.0)) for n in (12, 8, 8)]
    probe = torch.tensor(rng.normal(size=(12, 8, 8)))

    def gradient_and_saved_bytes():
        logits = torch.tensor([0.2, -0.1, 0.4], dtype=torch.float64, requires_grad=True)
        saved = []
        with torch.autograd.graph.saved_tensors_hooks(lambda t: saved.append(t.numel()) or t, lambda t: t):
            out = debiased_barycenter(log_density, torch.softmax(logits, 0), kernels, 36)
        (out * probe).sum().backward()
        return logits.grad, sum(saved)

    plain, plain_saved = gradient_and_saved_bytes()
    monkeypatch.setattr(wasserstein, "GRAPH_MEMORY_BYTES", 0)
    segmented, segmented_saved = gradient_and_saved_bytes()
    torch.testing.assert_close(segmented, plain, rtol=1e-12, atol=1e-15)
    assert segmented_saved < plain_saved / 4


@pytest.mark.parametrize("name", ["particle", "voxel"])
def test_muscles_can_start_as_the_environments_own(name):
    space = box_space()
    space.muscle = np.eye(4)[(space.points[:, 1] > 0.04).astype(int) + 2 * (space.points[:, 2] > 0.04)]  # not a grid
    muscle = build(name, space, muscle_init="environment", muscle_sharpness=8.0)().muscle.detach().numpy()
    own = muscle.argmax(1) == space.muscle.argmax(1)
    assert own.mean() > (0.999 if name == "particle" else 0.8)


def test_a_design_space_without_the_optional_fields_still_works():
    space = box_space(bare=True)
    for name in NEW:  # the workspace is the points' bounding box, fibres (but the primitives') the heading
        design = build(name, space)()
        assert design.occupancy.shape == (len(space.points),)
        if name in ("voxel", "implicit", "diff_cppn"):
            torch.testing.assert_close(design.fiber, torch.tensor([[1.0, 0.0, 0.0]]).expand(len(space.points), 3))


@pytest.mark.parametrize("name, config, message", [
    ("sdf_lerp", dict(primitives=["fish", "walrus"]), r"representation.primitives\[1\]: 'walrus' is neither"),
    ("wasserstein", dict(primitives=["no/such/file.obj"]), r"representation.primitives\[0\]"),
    ("voxel", dict(fiber=[0.0, 0.0, 0.0]), r"representation.fiber: \[0.0, 0.0, 0.0\] is not a non-zero"),
    ("implicit", dict(min_stiffness_ratio=2.0, max_stiffness_ratio=1.0), r"representation.min_stiffness_ratio"),
])
def test_bad_configs_are_recipe_errors(name, config, message):
    entry = get_registry().get("representation", name)
    with pytest.raises(RecipeError, match=message):
        entry.load_factory()(entry.load_config()(**config))


@pytest.mark.parametrize("name, config", [("particle", dict(muscle_init="random")), ("voxel", dict(muscle_init="random")),
                                          ("implicit", {}), ("diff_cppn", {})])
def test_a_symmetric_design_is_its_own_mirror_image_muscles_included(name, config):
    space = box_space()
    space.muscle = np.eye(4)[grid_partition(space.points, (2, 1, 2))]  # front/back x left/right
    representation = build(name, space, symmetric=True, **config)
    design = representation()
    mirror = representation._mirror
    assert sorted(mirror.actuator.tolist()) == [0, 1, 2, 3] and (mirror.actuator != np.arange(4)).all()
    np.testing.assert_array_equal(mirror.actuator[mirror.actuator], np.arange(4))  # left <-> right
    p = mirror.partner
    assert (p != np.arange(len(p))).mean() > 0.9
    for field in ("occupancy", "stiffness"):
        value = getattr(design, field).detach().numpy()
        np.testing.assert_allclose(value, value[p], rtol=1e-12)
    muscle = design.muscle.detach().numpy()
    np.testing.assert_allclose(muscle, muscle[p][:, mirror.actuator], rtol=1e-12)
    (design.occupancy.sum() + design.stiffness.sum() / E0 + (design.muscle[:, 0] * torch.tensor(space.points[:, 2])).sum()).backward()
    assert all(t.grad is not None and t.grad.abs().sum() > 0 for t in representation.parameters())


def test_a_symmetric_design_needs_a_bilateral_workspace():
    space = box_space()
    space.points = space.points[space.points[:, 2] < 0.06]  # a cut-off side
    space.bounds = np.stack([LO, HI])
    with pytest.raises(RecipeError, match="representation.symmetric: the design space is not bilateral"):
        build("voxel", space, symmetric=True)
