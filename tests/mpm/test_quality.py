"""Quality presets: each name resolves to the settings docs/accuracy.md states, explicit keys win,
unknown names are recipe errors that list the allowed ones. (No simulation: fast.)"""
import re
from pathlib import Path

import pytest

from codesign.errors import RecipeError
from codesign.recipe import resolve_section
from codesign_mpm.environment.config import PRESET_CONFIGS, LocomotionConfig, TerrainConfig
from codesign_mpm.scene.quality import QUALITY
from codesign_mpm.simulate import SceneFileError, load_scene

DOC = Path(__file__).resolve().parents[2] / "docs" / "accuracy.md"


def documented_presets() -> dict[str, dict]:
    """The preset table of docs/accuracy.md: name -> dx, particles per cell (robot, cover), cfl, dtype,
    checkpoint every."""
    rows = {}
    for line in DOC.read_text().splitlines():
        m = re.match(r"\| `(\w+)` \| 1/(\d+) \| (\d+) \| (\d+) \| ([\d.]+) \| (float\d+) \| ([^|]+) \|", line)
        if m:
            every = m.group(7).strip()
            rows[m.group(1)] = dict(dx=1 / int(m.group(2)), particles_per_cell=int(m.group(3)),
                                    cover_particles_per_cell=int(m.group(4)), cfl=float(m.group(5)),
                                    dtype=m.group(6), checkpoint_every=None if every.startswith("auto") else int(every))
    return rows


def test_each_preset_resolves_to_the_documented_settings():
    documented = documented_presets()
    assert list(documented) == ["draft", "default", "paper", "reference"] == list(QUALITY)
    for name, settings in documented.items():
        assert QUALITY[name].settings() == pytest.approx(settings), name
        config = PRESET_CONFIGS["desert"](quality=name, terrain=TerrainConfig(height=0.1))  # over 3 dx at draft too
        assert config.dx == pytest.approx(settings["dx"])
        assert (config.cfl, config.dtype, config.checkpoint_every) == (
            settings["cfl"], settings["dtype"], settings["checkpoint_every"])
        assert config.robot.particles_per_cell == settings["particles_per_cell"]
        assert config.cover.particles_per_cell == settings["cover_particles_per_cell"]


def test_the_default_preset_keeps_the_settings_recipes_had_before_presets():
    config = LocomotionConfig()
    assert (config.quality, config.dx, config.cfl, config.dtype, config.checkpoint_every,
            config.robot.particles_per_cell) == ("default", 1 / 48, 0.4, "float32", None, 8)


def test_explicit_keys_override_the_preset_in_a_recipe():
    section = resolve_section("environment", {"name": "desert", "quality": "reference", "dx": 0.05,
                                              "robot": {"particles_per_cell": 1}, "cfl": 0.5,
                                              "terrain": {"height": 0.2}})
    config, reference = section.config, QUALITY["reference"]
    assert (config.dx, config.cfl, config.robot.particles_per_cell) == (0.05, 0.5, 1)
    assert (config.dtype, config.cover.particles_per_cell) == (reference.dtype, reference.cover_particles_per_cell)


def test_a_preset_whose_dx_puts_the_terrain_in_the_wall_band_is_refused_when_the_recipe_is_read():
    """The default terrain (0.08 high) is under 3 dx at `draft` (dx 1/32): refused by validation,
    naming the key, its value and the least allowed, not first when the scene is built."""
    with pytest.raises(RecipeError, match=r"environment.terrain.height: 0.08 is below the wall band; "
                                          r"must be >= 3 dx = 0.09375"):
        resolve_section("environment", {"name": "ground", "quality": "draft"})


def test_an_unknown_preset_is_a_recipe_error_listing_the_allowed_names():
    with pytest.raises(RecipeError, match=r"environment\.quality.*'fast'.*draft, default, paper, reference"):
        resolve_section("environment", {"name": "ground", "quality": "fast"})
    with pytest.raises(RecipeError, match=r"environment\.quality: 'drafts'.*did you mean 'draft'"):
        LocomotionConfig(quality="drafts")


def test_a_scene_file_takes_a_preset_and_its_own_keys_win(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_text("quality: draft\ncfl: 0.3\nbodies:\n  - shape: {kind: box, size: [0.2, 0.2, 0.2]}\n"
                    "  - shape: {kind: box, size: [0.1, 0.1, 0.1]}\n    center: [0.2, 0.2, 0.2]\n"
                    "    particles_per_cell: 27\n")
    scene = load_scene(path)
    draft = QUALITY["draft"]
    assert (scene.dx, scene.dtype, scene.cfl) == (draft.dx, draft.dtype, 0.3)
    assert [b.particles_per_cell for b in scene.bodies] == [draft.particles_per_cell, 27]
    path.write_text("quality: best\nbodies: []\n")
    with pytest.raises(SceneFileError, match="quality: 'best'.*allowed: draft, default, paper, reference"):
        load_scene(path)


def test_a_scene_files_layer_takes_the_presets_cover_count(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_text("quality: paper\nbodies:\n  - shape: {kind: box, size: [0.1, 0.1, 0.1]}\n"
                    "  - shape: {kind: layer, thickness: 0.02}\n")
    paper = QUALITY["paper"]
    assert paper.cover_particles_per_cell != paper.particles_per_cell  # else this test cannot tell them apart
    scene = load_scene(path)
    assert [b.particles_per_cell for b in scene.bodies] == [paper.particles_per_cell, paper.cover_particles_per_cell]
