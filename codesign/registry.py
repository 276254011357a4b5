"""Name -> factory table for the four component kinds.

Entries refer to their factory and config dataclass by ``"module:attr"``
strings that are imported only when used, so listing or validating a recipe
never pulls in heavy code (Taichi, torch) for parts it does not build.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from codesign.errors import RegistryError

KINDS: tuple[str, ...] = ("environment", "representation", "controller", "optimizer")
"""The recipe's sections: one component of each kind makes a run."""
EXTENSION_KINDS: tuple[str, ...] = ("material",)
"""Kinds listed with the components but not recipe sections: material models of the MPM engine
(``codesign_register_materials``), which a scene names."""
ALL_KINDS = KINDS + EXTENSION_KINDS

#: A ``"module:attr"`` reference, or the object itself when laziness is not needed.
Ref = str | Callable[..., Any]


def suggest(word: str, known: Iterable[str]) -> str:
    """Return "did you mean 'x'? " for close matches of ``word`` in ``known``, or ""."""
    matches = difflib.get_close_matches(word, list(known), n=3)
    if not matches:
        return ""
    return "did you mean " + " or ".join(f"'{m}'" for m in matches) + "? "


def resolve_ref(ref: Ref) -> Any:
    """Import the object a ``"module:attr"`` reference names (objects pass through)."""
    if not isinstance(ref, str):
        return ref
    module_name, _, attr_path = ref.partition(":")
    obj: Any = importlib.import_module(module_name)
    for attr in attr_path.split("."):
        obj = getattr(obj, attr)
    return obj


@dataclass(frozen=True)
class Entry:
    """One registered component."""

    kind: str
    name: str
    factory: Ref
    """Called as ``factory(config)`` to build the component."""
    config: Ref
    """Dataclass describing (and validating) the recipe section's parameters."""
    description: str
    plugin: str
    distribution: str | None
    """Installed distribution that provides the plugin; None when loaded by module name."""

    def load_factory(self) -> Callable[[Any], Any]:
        return resolve_ref(self.factory)

    def load_config(self) -> type:
        schema = resolve_ref(self.config)
        if not (isinstance(schema, type) and dataclasses.is_dataclass(schema)):
            raise TypeError(f"config of {self.kind} '{self.name}' ({self.config!r}) is not a dataclass")
        return schema


class Registry:
    """All components known to this process, by kind and name."""

    def __init__(self) -> None:
        self._entries: dict[str, dict[str, Entry]] = {kind: {} for kind in ALL_KINDS}

    def add(
        self,
        kind: str,
        name: str,
        factory: Ref,
        config: Ref,
        description: str,
        *,
        plugin: str = "<direct>",
        distribution: str | None = None,
    ) -> Entry:
        """Register a component; a name may be used once per kind."""
        table = self._table(kind)
        for ref in (factory, config):
            if isinstance(ref, str) and ":" not in ref:
                raise RegistryError(f"{kind} '{name}': reference {ref!r} must look like 'module:attr'")
        if name in table:
            raise RegistryError(
                f"{kind} '{name}' is registered twice: by plugin '{table[name].plugin}' "
                f"and by plugin '{plugin}'"
            )
        entry = Entry(kind, name, factory, config, description, plugin, distribution)
        table[name] = entry
        return entry

    def get(self, kind: str, name: str) -> Entry:
        table = self._table(kind)
        if name not in table:
            known = sorted(table)
            raise RegistryError(
                f"unknown {kind} '{name}'; {suggest(name, known)}known: {', '.join(known) or '(none)'}"
            )
        return table[name]

    def entries(self, kind: str | None = None) -> list[Entry]:
        """Entries of one kind (or all), sorted by kind order then name."""
        kinds = ALL_KINDS if kind is None else (kind,)
        return [self._table(k)[n] for k in kinds for n in sorted(self._table(k))]

    def _table(self, kind: str) -> dict[str, Entry]:
        if kind not in self._entries:
            raise RegistryError(f"unknown kind '{kind}'; {suggest(kind, ALL_KINDS)}known: {', '.join(ALL_KINDS)}")
        return self._entries[kind]


class PluginRegistrar:
    """The view of a :class:`Registry` handed to one plugin's ``codesign_register`` hook.

    It records which plugin (and distribution) each entry came from, so plugins
    need not repeat their own name.
    """

    def __init__(self, registry: Registry, plugin: str, distribution: str | None) -> None:
        self._registry = registry
        self.plugin = plugin
        self.distribution = distribution

    def add(self, kind: str, name: str, factory: Ref, config: Ref, description: str) -> Entry:
        return self._registry.add(
            kind, name, factory, config, description, plugin=self.plugin, distribution=self.distribution
        )
