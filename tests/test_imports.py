import json
import os
import subprocess
import sys

from codesign.plugins import EXPLICIT_ENV

HEAVY = ("taichi", "torch", "wandb", "optuna", "ray")


def run_python(code: str) -> list[str]:
    """Run ``code`` with only the installed plugins; return the heavy modules it imported."""
    env = {k: v for k, v in os.environ.items() if k != EXPLICIT_ENV}
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_core_modules_and_plugin_loading_do_not_import_heavy_packages():
    code = (
        "import json, sys\n"
        "import codesign, codesign.cli, codesign.recipe, codesign.runner, codesign.tracking, codesign.sweep\n"
        "import codesign.progress, codesign.plots\n"
        "from codesign.plugins import get_registry\n"
        "get_registry()\n"
        f"print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))\n"
    )
    assert run_python(code) == []


def test_listing_plugins_and_showing_a_recipe_stay_light():
    # Validating a recipe imports only config modules, never the implementations.
    code = (
        "import json, sys\n"
        "from codesign.cli import main\n"
        "try:\n"
        "    main(['plugins', '--json'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "from codesign.plugins import get_registry\n"
        "for entry in get_registry().entries():\n"
        "    entry.load_config()\n"
        f"print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))\n"
    )
    assert run_python(code) == []
