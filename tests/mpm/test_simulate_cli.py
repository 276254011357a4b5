"""`codesign simulate`: scene files in, summary and per-frame export out, one-line user errors."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from codesign_mpm.scene.sampling import build_particles
from codesign_mpm.simulate import load_scene

SCENE = {
    "size": [0.5, 0.5, 0.5],
    "dx": 1 / 32,
    "terrain": {"kind": "flat", "height": 0.1},
    "bodies": [
        {"name": "ball", "shape": {"kind": "sphere", "radius": 0.05}, "center": [0.15, 0.3, 0.25]},
        {"name": "block", "shape": {"kind": "box", "size": [0.08, 0.08, 0.08]}, "center": [0.35, 0.3, 0.25],
         "material": {"kind": "corotated"}},
    ],
}


def write(tmp_path, data) -> str:
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_export_holds_every_frame_and_the_particle_labels(tmp_path, cli):
    scene_file, export = write(tmp_path, SCENE), tmp_path / "states.npz"
    code, out, _ = cli("simulate", scene_file, "--frames", "4", "--export", str(export), "--no-progress")
    assert code == 0
    assert "particles" in out and "substeps per frame" in out and "particle-substeps / s" in out
    particles = build_particles(load_scene(scene_file))
    n = particles.n
    data = np.load(export)
    assert {"x", "v", "material", "body", "frame_dt", "muscle", "robot", "actions", "dx", "height_map"} <= set(data.files)
    assert data["x"].shape == data["v"].shape == (5, n, 3) and data["x"].dtype == np.float32
    np.testing.assert_allclose(data["x"][0], particles.x, atol=1e-6)
    np.testing.assert_array_equal(data["v"][0], 0.0)
    np.testing.assert_array_equal(data["body"], particles.body)
    np.testing.assert_array_equal(data["material"], particles.material)
    assert set(data["body"]) == {0, 1} and len(set(data["material"])) == 2
    assert float(data["frame_dt"]) == pytest.approx(8e-3)
    fall = data["x"][1:, :, 1].mean(1)
    assert (np.diff(fall) < 0).all() and fall[0] < data["x"][0, :, 1].mean()  # falling under gravity
    np.testing.assert_allclose(data["v"][-1, :, 1].mean(), -3.8 * 4 * 8e-3, rtol=0.05)


@pytest.mark.parametrize("change, message", [
    (lambda s: s["bodies"][1]["shape"].update(sizes=[0.1, 0.1, 0.1]),
     "bodies[1].shape.sizes: Key 'sizes' not in 'ShapeSpec'"),
    (lambda s: s.update(gravty=[0, -1, 0]), "gravty: Key 'gravty' not in 'Scene'"),
    (lambda s: s["terrain"].update(friction="slippery"), "terrain.friction: Value 'slippery'"),
    (lambda s: s.update(dx=-0.1), "dx = -0.1 is invalid: must be > 0"),
    (lambda s: s["bodies"][0].update(material={"kind": "jelly"}), "bodies[0].material.kind = 'jelly' is invalid"),
])
def test_bad_scenes_give_one_red_line_naming_the_key(tmp_path, cli, change, message):
    scene = yaml.safe_load(yaml.safe_dump(SCENE))
    change(scene)
    code, out, err = cli("simulate", write(tmp_path, scene), "--frames", "1", "--no-progress")
    assert code == 1 and out == ""
    assert len(err.strip().splitlines()) == 1 and message in err and "Traceback" not in err


EXAMPLES = sorted((Path(__file__).resolve().parents[2] / "docs" / "scenes").glob("*.yaml"))


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.stem)
def test_example_scenes_load_and_simulate(path, cli):
    code, out, _ = cli("simulate", str(path), "--frames", "2", "--no-progress")
    assert code == 0 and "particle-substeps / s" in out


def test_a_mixed_scene_simulates_every_material_kind_together(tmp_path, cli):
    """One body of each non-elastic kind, dropped side by side with an elastic one."""
    kinds = ["sand", "snow", "clay", "water", "mud", "neo_hookean"]
    scene = {"size": [1.0, 0.4, 0.3], "dx": 1 / 32, "terrain": {"kind": "flat", "height": 0.1},
             "bodies": [{"name": kind, "shape": {"kind": "box", "size": [0.1, 0.1, 0.1]},
                         "material": {"kind": kind, "youngs_modulus": 2.0e4},
                         "center": [0.15 + 0.14 * i, 0.0, 0.15], "rest_on_terrain": True}
                        for i, kind in enumerate(kinds)]}
    export = tmp_path / "mixed.npz"
    code, _, _ = cli("simulate", write(tmp_path, scene), "--frames", "20", "--export", str(export),
                     "--no-progress")
    assert code == 0
    data = np.load(export)
    assert len(set(data["material"])) == len(kinds) and np.isfinite(data["x"]).all()
    assert data["x"][-1, :, 1].min() > 0.1 - 1 / 32  # nothing went through the terrain
