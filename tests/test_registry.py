import sys
from dataclasses import dataclass

import pytest

from codesign import CodesignError, RegistryError
from codesign.registry import PluginRegistrar, Registry


@dataclass
class Empty:
    pass


def make_registry() -> Registry:
    registry = Registry()
    registry.add("controller", "sine", "m:Sine", "m:SineConfig", "sine", plugin="basics")
    registry.add("controller", "mlp", "m:Mlp", "m:MlpConfig", "mlp", plugin="nets")
    registry.add("optimizer", "cma_es", "m:Cma", "m:CmaConfig", "cma", plugin="evo")
    return registry


def test_get_returns_the_entry_with_its_source():
    entry = make_registry().get("controller", "mlp")
    assert (entry.kind, entry.name, entry.factory, entry.plugin) == ("controller", "mlp", "m:Mlp", "nets")


def test_entries_are_grouped_by_kind_in_canonical_order_then_sorted_by_name():
    registry = make_registry()
    assert [(e.kind, e.name) for e in registry.entries()] == [
        ("controller", "mlp"),
        ("controller", "sine"),
        ("optimizer", "cma_es"),
    ]
    assert [e.name for e in registry.entries("controller")] == ["mlp", "sine"]
    assert registry.entries("environment") == []


def test_unknown_name_suggests_close_matches_and_lists_known_names():
    with pytest.raises(RegistryError) as info:
        make_registry().get("controller", "sinee")
    assert str(info.value) == "unknown controller 'sinee'; did you mean 'sine'? known: mlp, sine"
    assert isinstance(info.value, CodesignError)


def test_unknown_name_without_close_match_lists_known_names_only():
    with pytest.raises(RegistryError, match=r"^unknown optimizer 'ppo'; known: cma_es$"):
        make_registry().get("optimizer", "ppo")


def test_unknown_kind_is_an_error_with_suggestion():
    with pytest.raises(RegistryError, match="unknown kind 'controlers'; did you mean 'controller'"):
        make_registry().entries("controlers")


def test_duplicate_name_names_both_plugins():
    registry = make_registry()
    with pytest.raises(RegistryError, match="controller 'sine' is registered twice: by plugin 'basics' and by plugin 'other'"):
        registry.add("controller", "sine", "x:Y", "x:Z", "again", plugin="other")
    # the same name in another kind is fine
    registry.add("optimizer", "sine", "x:Y", "x:Z", "a sine-named optimizer")


def test_references_must_name_module_and_attribute():
    with pytest.raises(RegistryError, match="'module:attr'"):
        Registry().add("controller", "bad", "just_a_module", Empty, "bad ref")


def test_references_are_resolved_lazily_on_first_use():
    registry = Registry()
    module = "codesign_lazy_probe_does_not_exist"
    entry = registry.add("controller", "later", f"{module}:Thing", Empty, "not importable")
    assert module not in sys.modules
    with pytest.raises(ModuleNotFoundError):
        entry.load_factory()
    assert entry.load_config() is Empty


def test_string_references_resolve_nested_attributes():
    entry = Registry().add("controller", "path", "os:path.join", "codesign.recipe:TrackingConfig", "join")
    import os.path

    from codesign.recipe import TrackingConfig

    assert entry.load_factory() is os.path.join
    assert entry.load_config() is TrackingConfig


def test_config_that_is_not_a_dataclass_is_rejected_on_use():
    entry = Registry().add("controller", "odd", Empty, dict, "config is not a dataclass")
    with pytest.raises(TypeError, match="not a dataclass"):
        entry.load_config()


def test_registrar_attributes_entries_to_its_plugin():
    registry = Registry()
    PluginRegistrar(registry, "mine", "my-dist").add("controller", "c", Empty, Empty, "desc")
    entry = registry.get("controller", "c")
    assert (entry.plugin, entry.distribution) == ("mine", "my-dist")
