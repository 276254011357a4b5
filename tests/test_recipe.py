from dataclasses import dataclass, field
from pathlib import Path

import pytest

from codesign import RecipeError, recipe
from codesign.recipe import load_recipe, resolve_recipe
from codesign.registry import Registry
from codesign.sweep import plan_sweep


@dataclass
class Layer:
    width: int = field(default=16, metadata={"ge": 1})
    activation: str = field(default="tanh", metadata={"choices": ["tanh", "relu"]})


@dataclass
class NetConfig:
    hidden: list[Layer] = field(default_factory=lambda: [Layer(), Layer()])
    frequencies: list[float] = field(default_factory=lambda: [1.0, 2.0], metadata={"gt": 0})
    bound: float = field(default=0.3, metadata={"gt": 0, "le": 1})
    device: str = field(default="cpu", metadata={"choices": ["cpu", "cuda"]})


@dataclass
class StepsConfig:
    steps: int = field(metadata={"ge": 1})  # required: no default
    lr: float = 0.01


@dataclass
class NoConfig:
    pass


@pytest.fixture
def registry() -> Registry:
    r = Registry()
    r.add("environment", "flat", object, NoConfig, "")
    r.add("representation", "voxels", object, NoConfig, "")
    r.add("controller", "net", object, NetConfig, "")
    r.add("controller", "sine", object, NoConfig, "")
    r.add("optimizer", "adam", object, StepsConfig, "")
    return r


def base_data() -> dict:
    return {
        "environment": {"name": "flat"},
        "representation": {"name": "voxels"},
        "controller": {"name": "net"},
        "optimizer": {"name": "adam", "steps": 5},
    }


def error_of(registry, data, overrides=()) -> str:
    with pytest.raises(RecipeError) as info:
        resolve_recipe(data, overrides, default_name="r", registry=registry)
    return str(info.value)


def test_valid_recipe_fills_defaults_and_builds_config_objects(registry):
    resolved = resolve_recipe(base_data(), default_name="demo", registry=registry)
    assert resolved.name == "demo" and resolved.seed == 0
    assert resolved.settings.tracking.wandb is False and resolved.settings.tracking.wandb_mode == "offline"
    controller = resolved.sections["controller"]
    assert controller.name == "net"
    assert controller.config == NetConfig()
    assert resolved.sections["optimizer"].config == StepsConfig(steps=5)
    assert resolved.data["controller"]["hidden"] == [{"width": 16, "activation": "tanh"}] * 2
    assert resolved.data["optimizer"] == {"name": "adam", "steps": 5, "lr": 0.01}
    assert "controller:\n  name: net\n" in resolved.to_yaml()


def test_int_is_accepted_where_float_is_declared(registry):
    data = base_data()
    data["controller"]["bound"] = 1
    assert resolve_recipe(data, registry=registry).sections["controller"].config.bound == 1.0


def test_unknown_top_level_key(registry):
    message = error_of(registry, {**base_data(), "sed": 3})
    assert "sed: unknown key; did you mean 'seed'?" in message
    assert "allowed: name, seed, run_dir, tracking, render, sweep, init_controller, environment" in message


def test_unknown_key_inside_a_section(registry):
    data = base_data()
    data["controller"]["bonud"] = 0.2
    message = error_of(registry, data)
    assert "controller.bonud: unknown key; did you mean 'bound'? allowed: hidden, frequencies, bound, device" in message


def test_unknown_key_inside_nested_tracking(registry):
    message = error_of(registry, {**base_data(), "tracking": {"wandb": True, "projetc": "x"}})
    assert "tracking.projetc: unknown key; did you mean 'project'?" in message


def test_wrong_type(registry):
    data = base_data()
    data["optimizer"]["steps"] = "many"
    assert "optimizer.steps: expected int, got str 'many'" in error_of(registry, data)


def test_bool_is_not_accepted_as_a_number(registry):
    data = base_data()
    data["optimizer"]["steps"] = True
    assert "optimizer.steps: expected int, got bool True" in error_of(registry, data)


def test_out_of_range_number(registry):
    data = base_data()
    data["controller"]["bound"] = 1.5
    assert "controller.bound: 1.5 is out of range; must be > 0 and <= 1" in error_of(registry, data)


def test_invalid_choice(registry):
    data = base_data()
    data["controller"]["device"] = "cdua"
    assert "controller.device: 'cdua' is not a valid choice; did you mean 'cuda'? allowed: cpu, cuda" in error_of(
        registry, data
    )


def test_invalid_choice_in_top_level_schema(registry):
    message = error_of(registry, {**base_data(), "tracking": {"wandb_mode": "online!"}})
    assert "tracking.wandb_mode: 'online!' is not a valid choice" in message
    assert "allowed: offline, disabled, online" in message


def test_unknown_registry_name(registry):
    data = base_data()
    data["controller"] = {"name": "sinee"}
    assert "controller.name: unknown controller 'sinee'; did you mean 'sine'? known: net, sine" in error_of(
        registry, data
    )


def test_missing_required_value(registry):
    data = base_data()
    del data["optimizer"]["steps"]
    assert "optimizer.steps: missing required value (int)" in error_of(registry, data)


def test_missing_section_and_missing_name(registry):
    data = base_data()
    del data["environment"]
    data["controller"] = {"bound": 0.2}
    message = error_of(registry, data)
    assert "environment: missing required section (a mapping with 'name:'; known environments: flat)" in message
    assert "controller.name: missing required value (known controllers: net, sine)" in message


def test_nested_list_element_errors_carry_the_full_path(registry):
    data = base_data()
    data["controller"]["hidden"] = [{"width": 8}, {"width": 0}, {"activation": "sigmoid"}]
    data["controller"]["frequencies"] = [1.0, -2.0]
    message = error_of(registry, data)
    assert "controller.hidden[1].width: 0 is out of range; must be >= 1" in message
    assert "controller.hidden[2].activation: 'sigmoid' is not a valid choice; allowed: tanh, relu" in message
    assert "controller.frequencies[1]: -2.0 is out of range; must be > 0" in message


def test_all_problems_are_reported_together(registry):
    data = base_data()
    data["controller"]["bound"] = 0
    data["optimizer"]["lr"] = "fast"
    message = error_of(registry, data)
    assert message.startswith("invalid recipe 'r': ")
    assert "controller.bound" in message and "optimizer.lr" in message


def test_overrides_are_applied_and_typed(registry):
    resolved = resolve_recipe(
        base_data(),
        ["seed=3", "controller.bound=0.5", "controller.frequencies=[3,4]", "tracking.group=sweep1"],
        registry=registry,
    )
    assert resolved.seed == 3
    assert resolved.sections["controller"].config.bound == 0.5
    assert resolved.sections["controller"].config.frequencies == [3.0, 4.0]
    assert resolved.settings.tracking.group == "sweep1"


def test_override_to_an_unknown_key_is_an_error_that_names_the_override(registry):
    message = error_of(registry, base_data(), ["controller.bonud=0.2"])
    assert "controller.bonud: unknown key; did you mean 'bound'?" in message
    assert "(from override 'controller.bonud=0.2')" in message


def test_malformed_override(registry):
    assert "override 'seed': expected key=value" in error_of(registry, base_data(), ["seed"])


def test_override_changing_a_section_name_starts_that_section_afresh(registry):
    data = base_data()
    data["controller"]["bound"] = 0.2  # meaningful to 'net' only
    resolved = resolve_recipe(data, ["controller.name=sine"], registry=registry)
    assert resolved.sections["controller"].name == "sine"


def test_interpolations_are_resolved(registry):
    data = {**base_data(), "seed": 4, "tracking": {"group": "seed-${seed}"}}
    assert resolve_recipe(data, registry=registry).settings.tracking.group == "seed-4"


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_base_chain_with_relative_paths(tmp_path, registry):
    write(
        tmp_path / "common" / "root.yaml",
        "name: root\nseed: 1\nenvironment: {name: flat}\nrepresentation: {name: voxels}\n"
        "controller: {name: net, bound: 0.1, device: cuda}\noptimizer: {name: adam, steps: 2}\n",
    )
    write(tmp_path / "common" / "middle.yaml", "base: root.yaml\nseed: 2\ncontroller: {bound: 0.2}\n")
    child = write(tmp_path / "exp" / "child.yaml", "base: ../common/middle.yaml\noptimizer: {lr: 0.5}\n")
    resolved = load_recipe(child, ["optimizer.steps=9"], registry=registry)
    assert resolved.name == "child"  # named after the file, not its base
    assert resolved.seed == 2
    controller = resolved.sections["controller"].config
    assert (controller.bound, controller.device) == (0.2, "cuda")  # deep merge keeps the base's device
    assert resolved.sections["optimizer"].config == StepsConfig(steps=9, lr=0.5)


def test_base_cycle_is_detected(tmp_path, registry):
    write(tmp_path / "a.yaml", "base: b.yaml\n")
    write(tmp_path / "b.yaml", "base: a.yaml\n")
    with pytest.raises(RecipeError, match=r"recipe base cycle: .*a\.yaml -> .*b\.yaml -> .*a\.yaml"):
        load_recipe(tmp_path / "a.yaml", registry=registry)


def test_missing_base_names_the_file(tmp_path, registry):
    write(tmp_path / "a.yaml", "base: nowhere.yaml\n")
    with pytest.raises(RecipeError, match="recipe 'nowhere.yaml' not found"):
        load_recipe(tmp_path / "a.yaml", registry=registry)


def test_bare_name_is_found_in_the_recipes_directory(tmp_path, monkeypatch, registry):
    write(tmp_path / "recipes" / "walker.yaml", "seed: 5\n" + "".join(f"{k}: {v}\n" for k, v in {
        "environment": "{name: flat}", "representation": "{name: voxels}",
        "controller": "{name: net}", "optimizer": "{name: adam, steps: 1}"}.items()))
    monkeypatch.setattr(recipe, "RECIPES_DIR", tmp_path / "recipes")
    monkeypatch.chdir(tmp_path / "recipes")  # no ./recipes here: found via RECIPES_DIR
    resolved = load_recipe("walker", registry=registry)
    assert (resolved.name, resolved.seed) == ("walker", 5)
    with pytest.raises(RecipeError, match="recipe 'walkre' not found.*did you mean 'walker'"):
        load_recipe("walkre", registry=registry)


def test_invalid_yaml_is_a_recipe_error(tmp_path, registry):
    write(tmp_path / "bad.yaml", "seed: [1, 2\n")
    with pytest.raises(RecipeError, match="cannot read recipe"):
        load_recipe(tmp_path / "bad.yaml", registry=registry)


@pytest.mark.parametrize("path", sorted((Path(__file__).resolve().parents[1] / "recipes").glob("*.yaml")),
                         ids=lambda p: p.name)
def test_every_shipped_recipe_validates(path):
    """Each recipe in recipes/ composes and names existing components with valid settings (and a
    valid sweep, if it has one)."""
    recipe = load_recipe(path)
    assert set(recipe.sections) == {"environment", "representation", "controller", "optimizer"}
    if recipe.settings.sweep is not None:
        assert plan_sweep(recipe).seeds
