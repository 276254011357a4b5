"""Plugin discovery and the process-wide registry.

Like pytest, first-party plugins are found the same way as third-party ones:
through the ``codesign.plugins`` entry-point group. Controls:

- ``--disable-plugin NAME`` (CLI, repeatable) or ``CODESIGN_DISABLE_PLUGINS=a,b``
  blocks plugins by name;
- ``CODESIGN_DISABLE_PLUGIN_AUTOLOAD=1`` skips entry points altogether;
- ``CODESIGN_PLUGINS=module1,module2`` imports and registers plugin modules
  explicitly (also when autoloading is off).
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Iterable
from importlib.metadata import entry_points

import pluggy

from codesign import ENTRY_POINT_GROUP, hookspecs
from codesign.errors import PluginError
from codesign.registry import PluginRegistrar, Registry

DISABLE_ENV = "CODESIGN_DISABLE_PLUGINS"
NO_AUTOLOAD_ENV = "CODESIGN_DISABLE_PLUGIN_AUTOLOAD"
EXPLICIT_ENV = "CODESIGN_PLUGINS"


class PluginManager(pluggy.PluginManager):
    """A pluggy manager that remembers which distribution each plugin came from."""

    def __init__(self) -> None:
        super().__init__("codesign")
        self.add_hookspecs(hookspecs)
        self.distributions: dict[str, str | None] = {}

    def register_plugin(self, plugin: object, name: str, distribution: str | None) -> None:
        if self.get_plugin(name) is not None:
            other = self.distributions.get(name)
            raise PluginError(
                f"two plugins are named '{name}' (from {other or 'a module'} and {distribution or 'a module'})"
            )
        self.register(plugin, name=name)
        self.distributions[name] = distribution

    def build_registry(self) -> Registry:
        """Ask every plugin's ``codesign_register`` for its entries."""
        registry = Registry()
        # Called one plugin at a time so each entry is attributed to its plugin.
        for impl in reversed(self.hook.codesign_register.get_hookimpls()):
            registrar = PluginRegistrar(registry, impl.plugin_name, self.distributions.get(impl.plugin_name))
            impl.function(**({"registry": registrar} if "registry" in impl.argnames else {}))
        for impl in reversed(self.hook.codesign_register_materials.get_hookimpls()):
            registrar = PluginRegistrar(registry, impl.plugin_name, self.distributions.get(impl.plugin_name))
            for module_name in impl.function():
                try:
                    model = importlib.import_module(module_name).MODEL
                except (ImportError, AttributeError) as exc:
                    raise PluginError(f"plugin '{impl.plugin_name}': material module '{module_name}' "
                                      f"(a module defining MODEL) could not be loaded: {exc}") from exc
                registrar.add("material", model.name, f"{module_name}:MODEL", f"{module_name}:MODEL.config",
                              model.description)
        return registry


def _env_list(name: str) -> list[str]:
    return [item.strip() for item in os.environ.get(name, "").split(",") if item.strip()]


def create_plugin_manager(disabled: Iterable[str] = ()) -> PluginManager:
    """Load plugins from entry points and ``CODESIGN_PLUGINS``, minus the disabled ones."""
    pm = PluginManager()
    for name in {*disabled, *_env_list(DISABLE_ENV)}:
        pm.set_blocked(name)
    if os.environ.get(NO_AUTOLOAD_ENV, "") in ("", "0"):
        for ep in entry_points(group=ENTRY_POINT_GROUP):
            if pm.is_blocked(ep.name):
                continue
            try:
                plugin = ep.load()
            except Exception as exc:
                raise PluginError(f"could not load plugin '{ep.name}' ({ep.value}): {exc}") from exc
            pm.register_plugin(plugin, ep.name, ep.dist.name if ep.dist else None)
    for module_name in _env_list(EXPLICIT_ENV):
        if pm.is_blocked(module_name):
            continue
        try:
            module = importlib.import_module(module_name)
        except ImportError as exc:
            raise PluginError(f"could not import plugin module '{module_name}' from {EXPLICIT_ENV}: {exc}") from exc
        pm.register_plugin(module, module_name, None)
    return pm


_plugin_manager: PluginManager | None = None
_registry: Registry | None = None


def load_plugins(disabled: Iterable[str] = ()) -> PluginManager:
    """(Re)load all plugins and make them, and their registry, process-wide."""
    global _plugin_manager, _registry
    _plugin_manager = create_plugin_manager(disabled)
    _registry = _plugin_manager.build_registry()
    return _plugin_manager


def get_plugin_manager() -> PluginManager:
    """The process-wide plugin manager, loaded with defaults on first use."""
    if _plugin_manager is None:
        return load_plugins()
    return _plugin_manager


def get_registry() -> Registry:
    """The process-wide registry, built on first use."""
    if _registry is None:
        load_plugins()
    assert _registry is not None
    return _registry


def reset() -> None:
    """Forget the loaded plugins so the next use reloads them (for tests)."""
    global _plugin_manager, _registry
    _plugin_manager = _registry = None
