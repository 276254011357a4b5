import pytest

from codesign import PluginError, plugins

import toy_plugin


def names(kind: str) -> list[str]:
    return [e.name for e in plugins.get_registry().entries(kind)]


def test_entry_point_plugins_and_explicit_modules_are_both_loaded():
    registry = plugins.get_registry()
    sine = registry.get("controller", "sine")
    assert (sine.plugin, sine.distribution) == ("basics", "codesign")
    toy = registry.get("environment", "toy")
    assert (toy.plugin, toy.distribution) == ("toy_plugin", None)


def test_registry_is_built_once_per_process_until_reset():
    first = plugins.get_registry()
    assert plugins.get_registry() is first
    plugins.reset()
    assert plugins.get_registry() is not first


def test_disable_by_name_argument():
    plugins.load_plugins(disabled=["basics"])
    assert "sine" not in names("controller")
    assert "toy" in names("environment")


def test_disable_by_environment_variable(monkeypatch):
    def loaded() -> set[str]:
        return {entry.plugin for entry in plugins.get_registry().entries()}

    everything = loaded()
    monkeypatch.setenv(plugins.DISABLE_ENV, "toy_plugin, basics")
    plugins.reset()
    assert everything - loaded() == {"toy_plugin", "basics"}


def test_autoload_off_skips_entry_points_but_keeps_explicit_modules(monkeypatch):
    monkeypatch.setenv(plugins.NO_AUTOLOAD_ENV, "1")
    assert "sine" not in names("controller")
    assert "toy" in names("environment")


def test_explicit_module_that_cannot_be_imported_is_a_plugin_error(monkeypatch):
    monkeypatch.setenv(plugins.EXPLICIT_ENV, "toy_plugin,no_such_plugin_module")
    with pytest.raises(PluginError, match="could not import plugin module 'no_such_plugin_module'"):
        plugins.get_registry()


def test_same_plugin_name_twice_is_an_error(monkeypatch):
    monkeypatch.setenv(plugins.EXPLICIT_ENV, "toy_plugin,toy_plugin")
    with pytest.raises(PluginError, match="two plugins are named 'toy_plugin'"):
        plugins.get_registry()


def test_seed_hook_reaches_plugins():
    toy_plugin.seeds.clear()
    plugins.get_plugin_manager().hook.codesign_seed(seed=11)
    assert toy_plugin.seeds == [11]
