"""What validates, builds: every check an environment makes when it is built is made when its recipe
is read (`codesign show`, `run`, `sweep` and `study` read recipes the same way), so no run, sweep or
study finds a bad value only after its first runs. Every shipped recipe, and the quick start in
every environment, at each quality preset: read, then built; a refusal must come at reading."""

from pathlib import Path

import pytest

from codesign.errors import RecipeError
from codesign.recipe import load_recipe
from codesign.runner import build_parts
from codesign_mpm.environment.config import PRESETS
from codesign_mpm.scene.quality import QUALITY

RECIPES = sorted((Path(__file__).parents[2] / "recipes").glob("*.yaml"))
CASES = [(recipe, []) for recipe in RECIPES] + [(RECIPES[0].parent / "quickstart.yaml", [f"environment.name={name}"])
                                                for name in PRESETS]


@pytest.mark.parametrize("quality", list(QUALITY))
def test_every_recipe_that_validates_at_a_preset_builds(quality):
    built, refused = 0, []
    for recipe, extra in CASES:
        overrides = [*extra, f"environment.quality={quality}", "environment.dx=null"]
        try:
            resolved = load_recipe(recipe, overrides)
        except RecipeError as error:
            refused.append(str(error))
            continue
        try:
            environment = build_parts(resolved).environment
        except Exception as error:  # noqa: BLE001 - any failure here is a check that reading missed
            pytest.fail(f"{recipe.name} {' '.join(overrides)} validated but does not build: {error}")
        environment.close()
        built += 1
    assert built >= len(RECIPES) // 2, refused  # the check is not empty: most recipes hold at every preset
    assert all("environment." in message for message in refused), refused  # refusals name their key
