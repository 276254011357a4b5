"""Recipes: YAML files that name and parameterise the four parts of a run.

A recipe is composed (``base:`` chains, then ``key=value`` overrides),
interpolations (``${seed}``) are resolved with OmegaConf, and the result is
validated against the top-level schema and against each registry entry's
config dataclass before anything is built. See docs/recipes.md.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from codesign.errors import RecipeError, RegistryError
from codesign.registry import KINDS, Registry, suggest
from codesign.schema import Problem, convert, deep_merge, join

#: The repository's recipe directory, where bare recipe names are looked up (besides ./recipes).
RECIPES_DIR = Path(__file__).resolve().parent.parent / "recipes"
_SUFFIXES = (".yaml", ".yml")


@dataclass
class TrackingConfig:
    wandb: bool = field(default=False, metadata={"help": "also log to Weights & Biases"})
    wandb_mode: str = field(
        default="offline",
        metadata={"choices": ["offline", "disabled", "online"],
                  "help": "offline runs sync later with `wandb sync`; disabled (here or in $WANDB_MODE) starts no W&B"},
    )
    project: str = "codesign"
    group: str | None = None


@dataclass
class RenderConfig:
    """Rendering the best episode when a run ends, through whichever plugin implements
    ``codesign_render_run`` (codesign_mpm for its environments)."""

    enabled: bool = field(default=False, metadata={"help": "write best/episode.mp4 when the run ends"})
    camera: str = field(default="oblique", metadata={"choices": ["side", "top", "oblique"]})
    fps: int = field(default=25, metadata={"ge": 1})


@dataclass
class SweepMetric:
    name: str = field(default="best.episode_return", metadata={"help": "a key of the runs' summary.json, dotted"})
    goal: str = field(default="maximize", metadata={"choices": ["maximize", "minimize"]})


@dataclass
class SweepConfig:
    """A sweep in W&B's sweep-config form (method, metric, parameters) plus where trials run;
    ``codesign sweep`` reads it (see codesign.sweep and docs/sweeps.md), ``codesign run`` ignores it."""

    method: str = field(metadata={"choices": ["grid", "random", "bayes"]})
    parameters: dict[str, Any] = field(metadata={"help": "dotted recipe key -> values / value / distribution"})
    metric: SweepMetric = field(default_factory=SweepMetric)
    trials: int | None = field(default=None, metadata={"ge": 1, "help": "configurations to try (grid: all)"})
    seed: int = field(default=0, metadata={"ge": 0, "lt": 2**32, "help": "seeds the sampler"})
    backend: str = field(default="local", metadata={"choices": ["local", "ray"]})


@dataclass
class RecipeSettings:
    """The top-level keys of a recipe other than the four component sections."""

    name: str
    seed: int = field(default=0, metadata={"ge": 0, "lt": 2**32})
    run_dir: str | None = field(default=None, metadata={"help": "default: runs/<name>-<YYYYmmdd-HHMMSS>"})
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    sweep: SweepConfig | None = None
    init_controller: str | None = field(default=None, metadata={
        "help": "a run directory whose best controller (best/controller.pt) the controller starts from, e.g. "
                "to optimise designs under a pretrained gait; null: the controller's own initialisation"})


@dataclass(frozen=True)
class Section:
    """One component of a recipe: its registry name and validated config object."""

    name: str
    config: Any


@dataclass(frozen=True)
class ResolvedRecipe:
    """A composed, validated recipe, ready for the runner."""

    settings: RecipeSettings
    sections: dict[str, Section]
    """Keyed by kind: environment, representation, controller, optimizer."""
    data: dict
    """Plain resolved data with defaults filled in; saving it reproduces the recipe."""

    @property
    def name(self) -> str:
        return self.settings.name

    @property
    def seed(self) -> int:
        return self.settings.seed

    def to_yaml(self) -> str:
        return OmegaConf.to_yaml(OmegaConf.create(self.data))


def load_recipe(
    path_or_name: str | Path, overrides: Sequence[str] = (), *, registry: Registry | None = None
) -> ResolvedRecipe:
    """Load a recipe file (or a bare name from ``recipes/``), apply overrides, validate."""
    path = find_recipe(str(path_or_name))
    data = compose(path)
    return resolve_recipe(data, overrides, default_name=path.stem, registry=registry)


def resolve_recipe(
    data: Mapping[str, Any],
    overrides: Sequence[str] = (),
    *,
    default_name: str = "recipe",
    registry: Registry | None = None,
) -> ResolvedRecipe:
    """Apply ``key=value`` overrides to plain recipe data and validate the result."""
    if registry is None:
        from codesign.plugins import get_registry

        registry = get_registry()
    override_data = parse_overrides(overrides)
    merged = merge_recipes({"name": default_name, **data}, override_data)
    try:
        resolved = OmegaConf.to_container(OmegaConf.create(merged), resolve=True)
    except OmegaConfBaseException as exc:
        raise RecipeError(f"recipe '{merged.get('name')}': {_first_line(exc)}") from exc
    assert isinstance(resolved, dict)

    problems: list[Problem] = []
    allowed = [f.name for f in dataclasses.fields(RecipeSettings)] + list(KINDS)
    for key in resolved:
        if key not in allowed:
            problems.append(Problem(str(key), f"unknown key; {suggest(str(key), allowed)}allowed: {', '.join(allowed)}"))
    settings, found = convert(RecipeSettings, {k: v for k, v in resolved.items() if k not in KINDS})
    problems += found
    sections = {kind: _section(kind, resolved.get(kind), registry, problems) for kind in KINDS}
    if problems or settings is None:
        lines = [_with_origin(p, overrides) for p in problems]
        name = resolved.get("name", default_name)
        raise RecipeError(f"invalid recipe '{name}': " + "\n  ".join(lines))

    plain = {
        **dataclasses.asdict(settings),
        **{kind: {"name": s.name, **dataclasses.asdict(s.config)} for kind, s in sections.items()},
    }
    return ResolvedRecipe(settings, sections, plain)


def resolve_section(kind: str, data: Mapping[str, Any], *, registry: Registry | None = None) -> Section:
    """Validate one component section (``name`` plus parameters) as a recipe would."""
    if registry is None:
        from codesign.plugins import get_registry

        registry = get_registry()
    problems: list[Problem] = []
    section = _section(kind, dict(data), registry, problems)
    if problems or section is None:
        raise RecipeError(f"invalid {kind}: " + "\n  ".join(map(str, problems)))
    return section


def find_recipe(ref: str, relative_to: Path | None = None) -> Path:
    """Resolve a recipe path (relative to ``relative_to`` or the cwd), else a bare name in ``recipes/``."""
    direct = (relative_to / ref) if relative_to else Path(ref)
    if direct.is_file():
        return direct
    search_dirs = list(dict.fromkeys([Path.cwd() / "recipes", RECIPES_DIR]))
    if "/" not in ref and "\\" not in ref:
        for directory in search_dirs:
            for candidate in (directory / ref, *(directory / f"{ref}{s}" for s in _SUFFIXES)):
                if candidate.is_file():
                    return candidate
    known = sorted({p.stem for d in search_dirs if d.is_dir() for s in _SUFFIXES for p in d.glob(f"*{s}")})
    raise RecipeError(
        f"recipe '{ref}' not found (looked for {direct}); {suggest(Path(ref).stem, known)}"
        f"known names: {', '.join(known) or '(none)'}"
    )


def compose(path: Path, _chain: tuple[Path, ...] = ()) -> dict:
    """Read a recipe file and deep-merge it over its ``base:`` chain."""
    path = path.resolve()
    if path in _chain:
        cycle = " -> ".join(str(p) for p in (*_chain, path))
        raise RecipeError(f"recipe base cycle: {cycle}")
    data = _read_yaml(path)
    base = data.pop("base", None)
    if base is None:
        return data
    if not isinstance(base, str):
        raise RecipeError(f"{path}: base: expected a recipe path, got {base!r}")
    parent = compose(find_recipe(base, relative_to=path.parent), (*_chain, path))
    parent.pop("name", None)  # a recipe is named after itself, not its base
    return merge_recipes(parent, data)


def merge_recipes(base: Mapping[str, Any], child: Mapping[str, Any]) -> dict:
    """Deep-merge ``child`` over ``base``; lists and scalars are replaced.

    A component section whose ``name`` changes is replaced, not merged: the
    old component's parameters would mean nothing to the new one.
    """
    out = dict(base)
    for key, value in child.items():
        old = out.get(key)
        renamed = key in KINDS and isinstance(value, Mapping) and "name" in value and isinstance(old, Mapping) \
            and value["name"] != old.get("name")
        if isinstance(old, Mapping) and isinstance(value, Mapping) and not renamed:
            out[key] = deep_merge(old, value)
        else:
            out[key] = value
    return out


def _section(kind: str, raw: Any, registry: Registry, problems: list[Problem]) -> Section | None:
    known = ", ".join(e.name for e in registry.entries(kind)) or "(none)"
    if raw is None:
        problems.append(Problem(kind, f"missing required section (a mapping with 'name:'; known {kind}s: {known})"))
        return None
    if not isinstance(raw, Mapping):
        problems.append(Problem(kind, f"expected a mapping with 'name:' and parameters, got {raw!r}"))
        return None
    name = raw.get("name")
    if not isinstance(name, str):
        what = "missing required value" if name is None else f"expected str, got {name!r}"
        problems.append(Problem(join(kind, "name"), f"{what} (known {kind}s: {known})"))
        return None
    try:
        entry = registry.get(kind, name)
    except RegistryError as exc:
        problems.append(Problem(join(kind, "name"), str(exc)))
        return None
    config, found = convert(entry.load_config(), {k: v for k, v in raw.items() if k != "name"}, kind)
    problems += found
    return None if config is None else Section(name, config)


def parse_overrides(overrides: Iterable[str]) -> dict:
    """key=value strings (dotted keys) as the nested dict they set; a malformed one is a RecipeError."""
    for item in overrides:
        if "=" not in item or item.startswith("="):
            raise RecipeError(f"override '{item}': expected key=value (e.g. seed=3 or controller.bound=0.2)")
    try:
        parsed = OmegaConf.to_container(OmegaConf.from_dotlist(list(overrides)))
    except OmegaConfBaseException as exc:
        raise RecipeError(f"overrides {list(overrides)}: {_first_line(exc)}") from exc
    assert isinstance(parsed, dict)
    return parsed


def _with_origin(problem: Problem, overrides: Sequence[str]) -> str:
    for item in overrides:
        key = item.split("=", 1)[0]
        if problem.path == key or problem.path.startswith((f"{key}.", f"{key}[")):
            return f"{problem} (from override '{item}')"
    return str(problem)


def _read_yaml(path: Path) -> dict:
    try:
        data = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    except (OmegaConfBaseException, yaml.YAMLError, OSError) as exc:
        raise RecipeError(f"cannot read recipe {path}: {_first_line(exc)}") from exc
    if not isinstance(data, dict):
        raise RecipeError(f"recipe {path} must be a mapping at the top level")
    return data


def _first_line(exc: BaseException) -> str:
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
