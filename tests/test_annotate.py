"""The muscle annotator: k-means groups and PCA fibres of a body, its options and its command."""

import numpy as np
import pytest
import trimesh

from codesign.bodies import load_body
from codesign_designs.annotate import AnnotationError, annotate

ANGLES = (0.0, 60.0, 90.0)  # degrees about z of three bars laid out along x, left to right


def axis(angle: float) -> np.ndarray:
    return np.array([np.cos(np.radians(angle)), np.sin(np.radians(angle)), 0.0])


@pytest.fixture(scope="module")
def bars(tmp_path_factory):
    """Three separate elongated boxes at known angles: a synthetic body with known groups and axes."""
    parts = []
    for i, angle in enumerate(ANGLES):
        bar = trimesh.creation.box(extents=[1.2, 0.3, 0.3])
        bar.apply_transform(trimesh.transformations.rotation_matrix(np.radians(angle), [0, 0, 1]))
        parts.append(bar.apply_translation([2.0 * i, 0.0, 0.0]))
    path = tmp_path_factory.mktemp("bars") / "bars.stl"
    trimesh.util.concatenate(parts).export(path)
    return path


def test_k_means_recovers_the_bars_and_pca_their_axes(bars):
    result = annotate(load_body(bars), groups=3, resolution=60)
    x = result.points[:, 0]
    bar = np.digitize(x, [x.min() + (x.max() - x.min()) / 3, x.min() + 2 * (x.max() - x.min()) / 3])
    for g, angle in enumerate(ANGLES):  # numbered along x: group g is bar g, whole and alone
        assert set(result.groups[bar == g]) == {g}
        assert abs(result.axes[g] @ axis(angle)) > 0.995
    np.testing.assert_allclose(np.linalg.norm(result.fibers, axis=1), 1.0)
    assert (result.fibers[:, 0] >= -1e-12).all()  # fibres face the heading


def test_merged_and_passive_groups(bars):
    result = annotate(load_body(bars), groups=3, merge=[[1, 2]], passive=[0], resolution=40)
    assert result.group_names == ["k-means groups 1+2"]
    np.testing.assert_array_equal(result.groups, np.where(result.clusters == 0, -1, 0))
    union = result.points[result.groups == 0]  # the fibre is the principal axis of both bars together
    top = np.linalg.svd(union - union.mean(0), full_matrices=False)[2][0]
    assert abs(result.axes[0] @ top) > 1 - 1e-9


@pytest.mark.parametrize("options, message", [
    (dict(groups=0), r"--groups 0: must be at least 1"),
    (dict(groups=5000), r"--groups 5000: the body holds only \d+ samples"),
    (dict(groups=3, merge=[[1, 3]]), r"--merge 1,3: group 3 does not exist; groups are 0..2"),
    (dict(groups=3, merge=[[1, 1]]), r"--merge 1,1: a merge needs at least two different groups"),
    (dict(groups=3, merge=[[0, 1]], passive=[1]), r"--passive 1: group 1 is already used by --merge 0,1"),
    (dict(groups=2, passive=[0, 1]), r"every group is passive"),
])
def test_bad_options_are_refused_naming_the_option(bars, options, message):
    with pytest.raises(AnnotationError, match=message):
        annotate(load_body(bars), resolution=24, **options)


def test_the_command_writes_a_body_file_a_recipe_can_use_and_a_picture(bars, tmp_path, cli):
    out, png = tmp_path / "bars.annotated.npz", tmp_path / "bars.png"
    code, stdout, _ = cli("annotate", str(bars), "--groups", "3", "--merge", "0,1", "--out", str(out),
                          "--png", str(png), "--resolution", "32")
    assert code == 0 and f"wrote {out}" in stdout and "muscle 1: k-means group 2" in stdout
    body = load_body(out)
    assert body.group_names == ("k-means groups 0+1", "k-means group 2")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size < 100_000
    code, _, stderr = cli("annotate", str(bars), "--groups", "3", "--passive", "x", "--out", str(out))
    assert code == 1 and "--passive x: expected comma-separated group numbers" in stderr


def test_a_non_watertight_mesh_is_refused_by_the_command(tmp_path, cli):
    mesh = trimesh.creation.box()
    mesh.update_faces(np.arange(len(mesh.faces)) > 1)
    mesh.export(tmp_path / "open.stl")
    code, _, stderr = cli("annotate", str(tmp_path / "open.stl"), "--groups", "2")
    assert code == 1 and "open.stl: the mesh is not watertight" in stderr


def test_symmetric_annotation_gives_paired_limbs_mirrored_muscles(tmp_path):
    """Two legs splayed 30 degrees to either side: folded across the sagittal plane they are one
    cluster, split into a left and a right muscle whose samples and fibres are mirror images."""
    legs = []
    for side in (-1, 1):
        leg = trimesh.creation.box(extents=[0.3, 1.2, 0.3])
        leg.apply_transform(trimesh.transformations.rotation_matrix(np.radians(-30.0 * side), [1, 0, 0]))
        legs.append(leg.apply_translation([0.0, 0.0, 0.6 * side]))
    path = tmp_path / "legs.stl"
    trimesh.util.concatenate(legs).export(path)
    result = annotate(load_body(path), groups=1, symmetric=True, resolution=32)
    assert result.group_names == ["k-means group 0 left", "k-means group 0 right"]
    left, right = (result.points[result.groups == g] for g in (0, 1))
    mid = (result.points[:, 2].min() + result.points[:, 2].max()) / 2
    assert (left[:, 2] < mid).all() and (right[:, 2] >= mid).all() and len(left) == len(right)
    np.testing.assert_allclose(left.mean(0) * [1, 1, -1] + [0, 0, 2 * mid], right.mean(0), atol=1e-9)
    leg_axis = np.array([0.0, np.cos(np.radians(30.0)), -np.sin(np.radians(30.0))])  # the right leg leans in
    assert abs(result.axes[1] @ leg_axis) > 0.99 and abs(result.axes[0] @ (leg_axis * [1, 1, -1])) > 0.99
    plain = annotate(load_body(path), groups=1, resolution=32)
    assert plain.group_names == ["k-means group 0"]  # without it the two legs share one muscle
