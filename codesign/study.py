"""The paper's studies as one command: `codesign study NAME` (recipes/studies/NAME.yaml).

A study is a base recipe and a list of arms (the rows of one of the paper's tables), each arm a
few changes to the base and, where the paper has one, the paper's number for it. Every arm runs
as a sweep over the study's seeds (docs/sweeps.md), so a study is resumable the way a sweep is,
shows its progress and logs each run to W&B (offline by default). From the finished runs it
writes the table (returns in the paper's unit: the per-step mean of the task's reward, i.e. the
best episode's return divided by the horizon), a bar chart beside the paper's numbers, and a
Markdown section saying whether the paper's ordering of the arms holds at this scale.
"""
from __future__ import annotations

import copy
import csv
import importlib
import itertools
import json
import math
import re
import shutil
import statistics
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from omegaconf import OmegaConf
from scipy.stats import kendalltau

from codesign.artifacts import load_best_info
from codesign.errors import CodesignError, RecipeError
from codesign.recipe import RECIPES_DIR, deep_merge, compose, find_recipe, merge_recipes, resolve_recipe

STUDIES_DIR = "studies"  # under recipes/
DOCS_PAGE = Path("docs") / "studies.md"
DOCS_IMAGES = Path("docs") / "images" / "studies"
SCALE_DEFAULT = "cpu"
LISTED_ARMS = 6  # up to this many arms, the verdict spells out both orderings


@dataclass(frozen=True)
class Arm:
    """One row of a study's table: its label, its changes to the base recipe, the paper's value."""

    label: str
    set: dict[str, Any] = field(default_factory=dict)  # dotted recipe key -> value, merged into the base
    paper: float | None = None
    seeds: tuple[int, ...] | None = None  # its own seeds (an arm whose runs do not depend on the seed: one)
    reported: str | None = None  # "best" or "mean" over its seeds, as the paper reports this arm (None: the study's)
    cell: str | None = None  # a grid's arms: the labels but the last (the method): arms compared in one table cell

    @property
    def slug(self) -> str:
        return re.sub(r"[^a-z0-9]+", "_", self.label.lower()).strip("_")

    @property
    def parts(self) -> list[str]:
        """A grid arm's labels, one per dimension ("a / b / ..."); a listed arm's label alone."""
        return self.label.split(" / ")


@dataclass(frozen=True)
class Study:
    name: str
    title: str
    paper: str  # where the paper's numbers are, and its setup
    differs: str  # what differs from the paper's setup, for the docs
    seeds: tuple[int, ...]
    arms: tuple[Arm, ...]
    recipe: dict  # the base recipe, shared by every arm
    scale: str
    prepare: Arm | None = None  # a run made first (first seed), whose best controller arms start from
    analysis: str | None = None  # "module:function" measuring one robot instead of arms (codesign_mpm.reports.analyses)
    parameters: dict = field(default_factory=dict)  # the analysis's own settings
    still: bool = True  # also play each arm's starting design without any action (the return of doing nothing)
    prepared_arms: tuple[str, ...] | None = None  # labels of the arms that start from `prepare` (None: all)
    reported: str = "best"  # the value compared with the paper's: "best" of the seeds' runs, or their "mean"
    best_along: tuple[int, str] | None = None  # a grid's (dimension, its name): the paper reads which value does best


@dataclass(frozen=True)
class Row:
    """One arm's outcome over its seeds."""

    arm: Arm
    per_step: tuple[float, ...]  # each seed's best episode: return / horizon
    torn: tuple[float, ...]  # each seed's best episode: mass fraction torn off
    wall_time: tuple[float, ...]
    still: float | None = None  # the starting design with no action (first seed): return / horizon
    first: tuple[float, ...] = ()  # each seed's iteration 0 (its starting design and controller): return / horizon
    reported: str = "best"
    best_at_end: tuple[bool, ...] = ()  # each seed: whether its best iteration was its last (still improving)

    @property
    def mean(self) -> float:
        return statistics.fmean(self.per_step)

    @property
    def best(self) -> float:
        return max(self.per_step)

    @property
    def value(self) -> float:
        """What the table compares with the paper: the best of the seeds' runs, or their mean."""
        return self.best if self.reported == "best" else self.mean

    @property
    def std(self) -> float:
        """Over seeds (n - 1); nan for one seed."""
        return statistics.stdev(self.per_step) if len(self.per_step) > 1 else float("nan")

    @property
    def spread(self) -> float:
        """The standard deviation over seeds, 0 for one seed: what a difference must exceed to count."""
        return self.std if math.isfinite(self.std) else 0.0

    @property
    def moves(self) -> bool:
        """Whether it beats doing nothing by more than its spread over seeds (unknown no-action: yes)."""
        if self.still is None:
            return True
        return self.value - self.still > self.spread

    @property
    def gain(self) -> float:
        """Mean over seeds of the best episode's gain over the run's own iteration 0; nan when not logged."""
        if len(self.first) != len(self.per_step):
            return float("nan")
        return statistics.fmean(b - f for b, f in zip(self.per_step, self.first))


def separated(a: Row, b: Row) -> bool:
    """Whether two arms' reported values differ by more than the sum of their spreads over seeds."""
    return abs(a.value - b.value) > a.spread + b.spread


def _dotted(items: Mapping[str, Any]) -> dict:
    """{'a.b': 1} -> {'a': {'b': 1}} (values copied: the study's own data stays as read)."""
    nested: dict = {}
    for key, value in items.items():
        node = nested
        *parents, last = str(key).split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[last] = copy.deepcopy(value)
    return nested


def _grid_arms(grid: list, paper_table: Mapping, scale: str, where: str) -> list[dict]:
    """Arms for every combination of the grid's dimensions (each a list of {label, set, scales,
    only, reported, seeds}; a later dimension's keys win), labelled "a / b / ...", with the paper's number looked up
    in the nested `paper_table` by the labels in order (the last level may be a list, one number
    per label). A value with `only: [scales]` joins the grid at those scales alone."""
    arms = []
    for combination in itertools.product(*grid):
        if any(scale not in c.get("only", [scale]) for c in combination):
            continue
        labels = [c["label"] for c in combination]
        node: Any = paper_table
        for i, label in enumerate(labels):
            if isinstance(node, list):
                node = node[[c["label"] for c in grid[i]].index(label)] if len(node) == len(grid[i]) else None
            elif isinstance(node, Mapping):
                node = node.get(label)
            else:
                node = None
        arm = {"label": " / ".join(labels), "set": {k: v for c in combination for k, v in (c.get("set") or {}).items()},
               "paper": node if isinstance(node, (int, float)) else None, "cell": " / ".join(labels[:-1])}
        scales: dict = {}
        for c in combination:
            for name, changes in (c.get("scales") or {}).items():
                scales.setdefault(name, {}).update(changes)
        if scales:
            arm["scales"] = scales
        for key in ("reported", "seeds"):  # a later dimension's wins
            values = [c[key] for c in combination if key in c]
            if values:
                arm[key] = values[-1]
        arms.append(arm)
    if not arms:
        raise RecipeError(f"invalid {where}: study.grid: a dimension is empty")
    return arms


def find_study(ref: str) -> Path:
    """A study file: a path, or a name in recipes/studies/ (of the working directory or the package)."""
    if Path(ref).is_file():
        return Path(ref)
    directories = list(dict.fromkeys([Path.cwd() / "recipes" / STUDIES_DIR, RECIPES_DIR / STUDIES_DIR]))
    for directory in directories:
        for candidate in (directory / ref, directory / f"{ref}.yaml"):
            if candidate.is_file():
                return candidate
    known = sorted({p.stem for d in directories if d.is_dir() for p in d.glob("*.yaml")})
    raise RecipeError(f"study {ref!r} not found (a file, or a name in recipes/{STUDIES_DIR}/); "
                      f"known: {', '.join(known) or '(none)'}")


def load_study(ref: str, scale: str = SCALE_DEFAULT) -> Study:
    """A study file at one of its scales; its `recipe:` may start from a `base:` recipe file."""
    path = find_study(ref)
    where = f"study '{path.stem}'"
    try:
        raw = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    except Exception as exc:  # YAML syntax (yaml's own errors) or OmegaConf's
        raise RecipeError(f"invalid {where}: {path} does not read as YAML: {str(exc).splitlines()[0]}") from exc
    if not isinstance(raw, dict):
        raise RecipeError(f"invalid {where}: {path} holds no mapping (a 'study:' and a 'recipe:' section)")
    spec, recipe = raw.get("study"), raw.get("recipe")
    if not isinstance(spec, dict) or not isinstance(recipe, dict):
        raise RecipeError(f"invalid {where}: a study file needs a 'study:' section and a 'recipe:' section")
    if "base" in recipe:
        base = compose(find_recipe(str(recipe.pop("base")), relative_to=path.parent))
        base.pop("name", None)
        recipe = merge_recipes(base, recipe)
    analysis = spec.get("analysis")
    if spec.get("grid"):
        if spec.get("arms"):
            raise RecipeError(f"invalid {where}: study.arms and study.grid: give one of them")
        spec = {**spec, "arms": _grid_arms(spec["grid"], spec.get("paper_table") or {}, scale, where)}
    if not spec.get("arms") and analysis is None:
        raise RecipeError(f"invalid {where}: study.arms: empty; list the table's rows (label, set, paper), or "
                          f"name an analysis (study.analysis: module:function)")
    scales = spec.get("scales") or {}
    if scale != SCALE_DEFAULT and scale not in scales:
        raise RecipeError(f"invalid {where}: --scale {scale!r} is not a scale of this study; "
                          f"allowed: {', '.join([SCALE_DEFAULT, *scales])}")
    seeds = tuple(spec.get("seeds", [0, 1, 2]))
    if scale != SCALE_DEFAULT:
        changes = dict(scales[scale])
        seeds = tuple(changes.pop("seeds", seeds))
        changes.pop("parameters", None)
        recipe = merge_recipes(recipe, _dotted(changes))
    arms = []
    parameters = {**(spec.get("parameters") or {}), **(scales.get(scale, {}).get("parameters") or {})}
    for i, arm in enumerate(spec.get("arms") or []):
        unknown = set(arm) - {"label", "set", "paper", "scales", "seeds", "reported", "cell"}
        if "label" not in arm or unknown:
            raise RecipeError(f"invalid {where}: study.arms[{i}]: needs 'label' and takes set, paper, scales, seeds, "
                              f"reported" + (f"; unknown {', '.join(sorted(unknown))}" if unknown else ""))
        _check_reported(arm.get("reported"), f"{where}: study.arms[{i}].reported", optional=True)
        changes = {**(arm.get("set") or {}), **((arm.get("scales") or {}).get(scale) or {})}
        own = arm.get("seeds")
        if own is not None and (not isinstance(own, list) or not own or not all(isinstance(v, int) for v in own)):
            raise RecipeError(f"invalid {where}: study.arms[{i}].seeds: {own!r}; give a non-empty list of integers")
        chosen = (tuple(v for v in own if v in seeds) or seeds[:1]) if own is not None else None
        arms.append(Arm(arm["label"], changes, arm.get("paper"), chosen, arm.get("reported"), arm.get("cell")))
    prepare, prepared_arms = None, None
    if spec.get("prepare") is not None:
        spec_prepare = spec["prepare"]
        changes = {**(spec_prepare.get("set") or {}), **((spec_prepare.get("scales") or {}).get(scale) or {})}
        prepare = Arm(spec_prepare.get("label", "prepare"), changes)
        named = spec_prepare.get("arms")
        if named is not None:
            labels = [a.label for a in arms]
            if not isinstance(named, list) or not all(label in labels for label in named):
                raise RecipeError(f"invalid {where}: study.prepare.arms: {named!r}; give a list of arm labels "
                                  f"(the arms that start from its controller): {', '.join(labels)}")
            prepared_arms = tuple(named)
    if len({a.slug for a in arms}) != len(arms):
        raise RecipeError(f"invalid {where}: study.arms: two labels give the same directory name")
    reported = _check_reported(spec.get("reported", "best"), f"{where}: study.reported")
    return Study(path.stem, spec.get("title", path.stem), spec.get("paper", ""), spec.get("differs", ""),
                 seeds, tuple(arms), recipe, scale, prepare, analysis, parameters, bool(spec.get("still", True)),
                 prepared_arms, reported, _best_along(spec, where))


def _best_along(spec: dict, where: str) -> tuple[int, str] | None:
    """`study.best_along: {dimension: i, name: ...}`: a grid dimension (0-based) whose values the
    paper compares with the others held fixed (Table 1: which animal suits which environment)."""
    value = spec.get("best_along")
    if value is None:
        return None
    dimensions = len(spec.get("grid") or [])
    if (not isinstance(value, dict) or set(value) != {"dimension", "name"} or not isinstance(value["name"], str)
            or not isinstance(value["dimension"], int) or not 0 <= value["dimension"] < dimensions - 1):
        raise RecipeError(f"invalid {where}: study.best_along: {value!r}; give {{dimension: i, name: what its values "
                          f"are}} with i a grid dimension before the methods' (0 to {dimensions - 2})")
    return value["dimension"], value["name"]


REPORTED = ("best", "mean")


def _check_reported(value: Any, key: str, optional: bool = False) -> Any:
    if (value is None and optional) or value in REPORTED:
        return value
    raise RecipeError(f"invalid {key}: {value!r}; allowed: {', '.join(REPORTED)} (the best of an arm's seeds, as the "
                      f"paper reports diff-physics, or their mean, as it reports PPO)")


PREPARE_DIR = "prepare"
STILL_DIR = "still"


def prepare_recipe(study: Study) -> dict:
    """The recipe of the study's preparatory run: the base with its keys set, at the first seed."""
    assert study.prepare is not None
    return {**merge_recipes(study.recipe, _dotted(study.prepare.set)), "name": f"{study.name}-{PREPARE_DIR}",
            "seed": study.seeds[0]}


def _starts_from_prepare(study: Study, arm: Arm) -> bool:
    """Whether the study's preparatory run names this arm (or every arm)."""
    return study.prepare is not None and (study.prepared_arms is None or arm.label in study.prepared_arms)


def arm_recipe(study: Study, arm: Arm, root: Path = Path(STUDIES_DIR)) -> dict:
    """The recipe of one arm: the base with its keys set (a section given a new `name` is replaced,
    as in any recipe), swept over the study's seeds; with a preparatory run (in `root`) that names
    this arm or every arm, starting from its best controller."""
    changes = _dotted(arm.set)
    environment = changes.get("environment")
    if isinstance(environment, dict) and "name" in environment:  # presets share one schema: keep the base's keys
        changes["environment"] = deep_merge(study.recipe.get("environment") or {}, environment)
    data = merge_recipes(study.recipe, changes)
    if _starts_from_prepare(study, arm):
        data["init_controller"] = str(root / PREPARE_DIR)
    data["name"] = f"{study.name}-{arm.slug}"
    data["sweep"] = {"method": "grid", "metric": {"name": "best.episode_return", "goal": "maximize"},
                     "parameters": {"seed": {"values": list(arm_seeds(study, arm))}}}
    return data


def arm_seeds(study: Study, arm: Arm) -> tuple[int, ...]:
    """The seeds an arm runs: its own (`load_study` keeps those the scale runs), else the study's."""
    return arm.seeds or study.seeds


def still_recipe(study: Study, arm: Arm) -> dict:
    """One episode of the arm's starting design (first seed) with no action at all: what a body
    does by itself (sagging, tipping, drifting in settling water) scores this much, and a gait's
    return is worth what it adds to it."""
    data = arm_recipe(study, arm)
    for key in ("sweep", "init_controller"):
        data.pop(key, None)
    data.update(name=f"{study.name}-{arm.slug}-{STILL_DIR}", seed=arm_seeds(study, arm)[0],
                optimizer={"name": "evaluate", "episodes": 1},
                controller={"name": "sine", "init_std": 0.0})  # zero weights and biases: every action is 0
    return data


def still_dirs(study: Study, root: Path) -> dict[str, Path]:
    """Where each arm's no-action run lives: ARM/still/ of the first arm whose no-action recipe is the
    same (its name aside). Arms that differ only in how they optimise (Table 1's diff-physics and
    PPO) start from the same body and play the same still episode, once."""
    first: dict[str, Path] = {}
    where = {}
    for arm in study.arms:
        recipe = still_recipe(study, arm)
        recipe.pop("name")
        key = json.dumps(recipe, sort_keys=True)
        where[arm.slug] = first.setdefault(key, root / arm.slug / STILL_DIR)
    return where


def study_dir(study: Study, directory: str | Path | None) -> Path:
    if directory is not None:
        return Path(directory)
    suffix = "" if study.scale == SCALE_DEFAULT else f"-{study.scale}"
    return Path(STUDIES_DIR) / f"{study.name}{suffix}"


def select_arms(study: Study, parts: Sequence[str]) -> tuple[Arm, ...]:
    """The arms whose label has every one of `parts` among its " / "-separated parts (all for none):
    cheap arms first (e.g. Table 1's "Diff-physics"), the rest in a later run of the same study."""
    known = {part for arm in study.arms for part in arm.parts}
    unknown = [part for part in parts if part not in known]
    if unknown:
        raise CodesignError(f"--arm {unknown[0]!r}: no arm of study {study.name} has it; its arms' parts: "
                            + ", ".join(sorted(known)))
    chosen = tuple(arm for arm in study.arms if all(part in arm.parts for part in parts))
    if not chosen:
        raise CodesignError(f"--arm {' --arm '.join(map(repr, parts))}: no arm of study {study.name} has all of them")
    return chosen


def run_study(study: Study, directory: str | Path | None = None, *, progress: bool = True,
              backend: str | None = None, ray_address: str | None = None, arms: Sequence[str] = ()) -> Path:
    """Run every arm, or those `select_arms` picks from `arms` (an arm already under way or done is
    continued, not restarted); then tabulate every finished run. With `backend` "ray", the arms'
    runs at once as Ray tasks (see `_run_on_ray`)."""
    if backend not in (None, "local", "ray"):
        raise CodesignError(f"--backend {backend!r}: choose from local, ray")
    root = study_dir(study, directory)
    if study.analysis is not None:
        if backend == "ray" or arms:
            raise CodesignError(f"study {study.name} is an analysis (it measures points, not runs): "
                                f"run it without --backend ray or --arm")
        findings = _analysis(study.analysis)(study, root, progress)
        (root / "section.md").write_text(_heading(study) + findings.rstrip() + "\n\n" + _data_line(study) + "\n"
                                         + _differs(study), encoding="utf-8")
        return root
    for arm in study.arms:  # every arm checked before anything runs
        resolve_recipe(arm_recipe(study, arm, root), default_name=arm.slug)
    chosen = select_arms(study, arms)
    if backend == "ray":
        _run_on_ray(study, root, ray_address, progress, chosen)
    else:
        _run_here(study, root, progress, chosen)
    write_results(study, root, records_for_report(study, root))
    return root


def _needs_prepare(study: Study, chosen: tuple[Arm, ...]) -> bool:
    return any(_starts_from_prepare(study, arm) for arm in chosen)


def _own_stills(study: Study, root: Path, chosen: tuple[Arm, ...]) -> dict[str, Path]:
    """The no-action episodes `chosen` plays: those that live in a chosen arm's directory (`still_dirs`).
    One that lives in an arm not chosen waits for it: written first, it would leave that arm's
    directory non-empty before its sweep starts."""
    if not study.still:
        return {}
    mine = {root / arm.slug for arm in chosen}
    return {slug: still for slug, still in still_dirs(study, root).items() if still.parent in mine}


def _run_here(study: Study, root: Path, progress: bool, chosen: tuple[Arm, ...]) -> None:
    """The preparatory run, then arm after arm (of `chosen`): its seeds, then its no-action episode."""
    from codesign import sweep as sweeps

    if _needs_prepare(study, chosen) and not sweeps.finished(root / PREPARE_DIR):
        if progress:
            print(f"[{study.name}] first: {study.prepare.label}", file=sys.stderr, flush=True)
        sweeps.execute({**prepare_recipe(study), "run_dir": str(root / PREPARE_DIR)}, progress=progress)
    stills = _own_stills(study, root, chosen)
    for i, arm in enumerate(chosen):
        arm_dir = root / arm.slug
        resume = (arm_dir / sweeps.SWEEP_FILE).is_file()
        if progress:
            print(f"[{study.name}] arm {i + 1}/{len(chosen)}: {arm.label}"
                  + (" (continuing)" if resume else ""), file=sys.stderr, flush=True)
        _arm_sweep(arm_recipe(study, arm, root), arm_dir, resume, progress=progress)
        if arm.slug in stills and not sweeps.finished(stills[arm.slug]):
            sweeps.execute({**still_recipe(study, arm), "run_dir": str(stills[arm.slug])}, progress=progress)


def _arm_sweep(data: dict, arm_dir: Path, resume: bool, backend: str | None = None, progress: bool = False) -> None:
    """One arm's sweep over its seeds (also as a Ray task, whose seeds are Ray tasks of their own)."""
    from codesign import sweep as sweeps

    sweeps.run_sweep(resolve_recipe(data), sweep_dir=arm_dir, resume=resume, backend=backend, progress=progress)


def _play_after(arm_sweep: None, data: dict) -> str:
    """Run `data` once the arm sweep whose directory holds it is done (Ray passes a task's result
    only when it is ready): started beside it, it would leave the arm's directory non-empty before
    the sweep began, which a new sweep refuses."""
    from codesign import sweep as sweeps

    return sweeps.execute(data)


def _run_on_ray(study: Study, root: Path, address: str | None, progress: bool, chosen: tuple[Arm, ...]) -> None:
    """The preparatory run first (the arms it names start from it), then every arm's sweep at once,
    each a Ray task holding no CPU whose seeds run as Ray tasks of one CPU (one GPU where the
    cluster has them), and each no-action episode after the arm whose directory holds it. `root`
    must be on a filesystem that every node sees. A failed run stops nothing else; the finished
    runs are kept and a rerun continues from them."""
    from codesign import sweep as sweeps

    ray = sweeps.connect_ray(address)
    run = sweeps.run_task(ray)
    if _needs_prepare(study, chosen) and not sweeps.finished(root / PREPARE_DIR):
        if progress:
            print(f"[{study.name}] first: {study.prepare.label} (Ray)", file=sys.stderr, flush=True)
        ray.get(run.remote({**prepare_recipe(study), "run_dir": str(root / PREPARE_DIR)}))
    arm_task = ray.remote(num_cpus=0)(_arm_sweep)
    still_task = sweeps.run_task(ray, _play_after)
    jobs, arm_jobs = {}, {}
    for arm in chosen:
        arm_dir = root / arm.slug
        arm_jobs[arm_dir] = arm_task.remote(arm_recipe(study, arm, root), arm_dir,
                                            (arm_dir / sweeps.SWEEP_FILE).is_file(), "ray")
        jobs[arm_jobs[arm_dir]] = arm.label
    stills = _own_stills(study, root, chosen)
    for still, arm in {stills[arm.slug]: arm for arm in reversed(chosen) if arm.slug in stills}.items():
        if not sweeps.finished(still):  # each played once, from the first arm that shares it, after its owner's sweep
            jobs[still_task.remote(arm_jobs[still.parent], {**still_recipe(study, arm), "run_dir": str(still)})] = \
                f"no action ({still.parent.name})"
    if progress:
        print(f"[{study.name}] {len(chosen)} arms and {len(jobs) - len(chosen)} no-action episodes "
              f"on Ray", file=sys.stderr, flush=True)
    errors = []
    while jobs:
        (ref,), _ = ray.wait(list(jobs), num_returns=1)
        what = jobs.pop(ref)
        try:
            ray.get(ref)
        except Exception as exc:  # the others go on; their runs are kept
            errors.append(f"{what}: {type(exc).__name__}: {exc}")
            continue
        if progress:
            print(f"[{study.name}] done: {what}", file=sys.stderr, flush=True)
    if errors:
        raise CodesignError(f"{len(errors)} part(s) of study {study.name} failed (the finished runs are kept; fix "
                            f"the cause and run it again to continue):\n  " + "\n  ".join(errors))


RUNS_FILE = "runs.jsonl"  # what the table is built from: a header line, then one line per finished run
POINTS_FILE = "points.jsonl"  # an analysis's measurements, one line per point (codesign_mpm.reports.analyses)
DOCS_DATA = Path("docs") / "data" / "studies"


def _run_record(arm: Arm, run: Path) -> dict:
    """A finished run, compactly: its seed, horizon, every iteration's episode return (the first is
    its starting design and controller), its best return, torn-off mass and wall time."""
    from codesign.runner import CONFIG_FILE, METRICS_FILE, SUMMARY_FILE, read_metrics

    summary = json.loads((run / SUMMARY_FILE).read_text(encoding="utf-8"))
    config = OmegaConf.load(run / CONFIG_FILE)
    returns = [row["episode_return"] for row in read_metrics(run / METRICS_FILE) if "episode_return" in row]
    return {"arm": arm.label, "run": run.name, "seed": int(config.seed), "horizon": int(config.environment.horizon),
            "best": summary["best"]["episode_return"], "returns": returns,
            "torn": load_best_info(run).get("torn_fraction", float("nan")),  # environments with bodies
            "wall_time": summary["wall_time"]}


def extract(study: Study, root: Path) -> list[dict]:
    """The records of the study's finished runs in `root`, and of each arm's no-action episode
    (`still`); arms with none yet are left out (a study under way can be reported)."""
    from codesign import sweep as sweeps

    records = []
    stills = still_dirs(study, root)
    for arm in study.arms:
        for run in sorted((root / arm.slug).glob("t*-seed*")):
            if sweeps.finished(run):
                records.append(_run_record(arm, run))
        still = stills[arm.slug]
        if sweeps.finished(still):
            record = _run_record(arm, still)
            records.append({"arm": arm.label, "still": record["best"] / record["horizon"]})
    return records


def data_path(study: Study, repo: Path = Path(".")) -> Path:
    """Where a study's records are committed: docs/data/studies/NAME[-SCALE].jsonl (an analysis's
    points: NAME[-SCALE].points.jsonl)."""
    suffix = "" if study.scale == SCALE_DEFAULT else f"-{study.scale}"
    return repo / DOCS_DATA / f"{study.name}{suffix}{'.points' if study.analysis else ''}.jsonl"


def seed_points(study: Study, root: Path) -> bool:
    """For `--report` of an analysis: the committed points copied into `root` when it has none, so
    that running it measures nothing they hold. Whether they were."""
    committed = data_path(study)
    if (root / POINTS_FILE).is_file() or not committed.is_file():
        return False
    root.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(committed, root / POINTS_FILE)
    return True


def write_records(study: Study, records: list[dict], path: Path) -> None:
    header = {"study": study.name, "scale": study.scale}
    path.write_text("".join(json.dumps(r) + "\n" for r in [header, *records]), encoding="utf-8")


def read_records(path: Path) -> tuple[dict, list[dict]]:
    """(header, records) of a runs.jsonl."""
    lines = [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]
    if not lines or "study" not in lines[0]:
        raise CodesignError(f"{path} is not a study's records (its first line names no study)")
    return lines[0], lines[1:]


def rows_from(study: Study, records: list[dict]) -> list[Row]:
    """Each arm's row from its records, in the study's order of arms."""
    rows = []
    for arm in study.arms:
        runs = [r for r in records if r["arm"] == arm.label and "best" in r]
        if not runs:
            continue
        stills = [r["still"] for r in records if r["arm"] == arm.label and "still" in r]
        rows.append(Row(arm, tuple(r["best"] / r["horizon"] for r in runs), tuple(r["torn"] for r in runs),
                        tuple(r["wall_time"] for r in runs), stills[0] if stills else None,
                        tuple(r["returns"][0] / r["horizon"] for r in runs if r["returns"]),
                        arm.reported or study.reported,
                        tuple(r["returns"][-1] >= max(r["returns"]) for r in runs if len(r["returns"]) > 1)))
    if not rows:
        raise CodesignError(f"study {study.name}: no arm has a finished run; run `codesign study {study.name}` "
                            f"to (re)start it")
    return rows


def verdict(rows: list[Row]) -> str:
    """Whether the paper's ordering of the arms holds here (by each arm's reported value: the best of
    its seeds, or their mean), and which neighbours the seeds do not separate. A cell (a grid's
    methods for one task, body and environment; else the whole table) none of whose arms beats doing
    nothing by more than its spread over seeds is noise: said, not ranked."""
    cells: dict[str | None, list[Row]] = {}
    for r in rows:
        cells.setdefault(r.arm.cell, []).append(r)
    still = [r for cell in cells.values() if not any(c.moves for c in cell) for r in cell]
    noise = ("" if not still else f" Not ranked, no better than no action (by more than their spread over seeds): "
             f"{', '.join(r.arm.label for r in still)}.")
    weak = [r for r in rows if r not in still and not r.moves]
    if weak:  # named in either form of the verdict: which of the table's numbers a reader should not rank
        noise += (" No better than no action by more than their spread over seeds, ranked with the rest of their "
                  f"cell: {', '.join(r.arm.label + _still_improving(r) for r in weak)}.")
    compared = [r for r in rows if r.arm.paper is not None and r not in still]
    if len(compared) < 2:
        return "The paper gives fewer than two of these numbers: no ordering to compare." + noise
    paper_order = sorted(compared, key=lambda r: r.arm.paper, reverse=True)
    ours_order = sorted(compared, key=lambda r: r.value, reverse=True)
    tau = kendalltau([r.arm.paper for r in compared], [r.value for r in compared]).statistic
    agreement = f"Kendall's tau {tau:.2f}" if math.isfinite(tau) else "Kendall's tau undefined: tied values"
    unclear = [f"{a.arm.label} / {b.arm.label}" for a, b in zip(paper_order, paper_order[1:]) if not separated(a, b)]
    if len(compared) > LISTED_ARMS:  # a benchmark grid: the orderings are too long to read, the numbers are not
        swapped = sum((a.arm.paper - b.arm.paper) * (a.value - b.value) < 0 for i, a in enumerate(compared)
                      for b in compared[i + 1:])
        pairs = len(compared) * (len(compared) - 1) // 2
        return (f"Over the {len(compared)} arms with a number in the paper, ours order {pairs - swapped} of "
                f"{pairs} pairs as the paper's do ({agreement}); {len(unclear)} of the {len(compared) - 1} "
                f"neighbours in the paper's ordering differ by less than their standard deviations over seeds."
                + noise)
    names = " > ".join(r.arm.label for r in paper_order)
    if paper_order == ours_order:
        text = f"The paper's ordering ({names}) **holds** here ({agreement})."
    else:
        text = (f"The paper's ordering ({names}) **does not hold** here: ours is "
                f"{' > '.join(r.arm.label for r in ours_order)} ({agreement}).")
    if unclear:
        text += (" Closer than the sum of their standard deviations over seeds (not separated at this scale): "
                 + ", ".join(unclear) + ".")
    return text + noise


def _still_improving(row: Row) -> str:
    """The verdict's note on an arm: in how many seeds its best iteration was its last (the budget
    ended it still improving)."""
    if not row.best_at_end:
        return ""
    return f" (best at its last iteration in {sum(row.best_at_end)} of {len(row.best_at_end)} seeds)"


def best_along(rows: list[Row], dimension: int, name: str) -> str:
    """The paper's reading of a grid along one dimension: in each combination of the other labels
    (a grid arm's label is "a / b / ..."), which of this dimension's values scores best, ours against
    the paper's; a winner of ours is separated when it beats the runner-up by more than the sum of
    their standard deviations over seeds."""
    groups: dict[str, list[tuple[str, Row]]] = {}
    for r in rows:
        parts = r.arm.parts
        if r.arm.paper is not None and len(parts) > dimension:
            rest = " / ".join(parts[:dimension] + parts[dimension + 1:])
            groups.setdefault(rest, []).append((parts[dimension], r))
    agree, apart_count, differ = 0, 0, []
    compared = {rest: members for rest, members in groups.items() if len(members) > 1}
    for rest, members in compared.items():
        ours = sorted(members, key=lambda m: m[1].value, reverse=True)
        paper = max(members, key=lambda m: m[1].arm.paper)
        apart = separated(ours[0][1], ours[1][1])
        apart_count += apart
        if ours[0][0] == paper[0]:
            agree += 1
        else:
            differ.append(f"{rest}: ours {ours[0][0]} ({_fmt(ours[0][1].value)}"
                          f"{'' if apart else ', not separated'}), the paper's {paper[0]} ({paper[1].arm.paper:.3f})")
    if not compared:
        return f"No two {name}s with numbers here share the other labels: no {name} to compare."
    text = (f"Which {name} does best, the rest held fixed (the paper's reading of this table): ours is the "
            f"paper's in {agree} of {len(compared)} comparisons, and the seeds separate our best from the "
            f"runner-up (by more than the sum of their spreads) in {apart_count} of the {len(compared)}.")
    return text + (f" Where they differ: {'; '.join(differ)}." if differ else "")


def _fmt(v: float) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v:.4f}"


def _percent(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{v:.1%}"


def table_markdown(rows: list[Row]) -> str:
    lines = ["| arm | ours: per-step return, reported | best | mean | std over seeds | seeds | gain over iteration 0 "
             "| no action | paper | torn-off mass (max) | wall s (mean) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {r.arm.label} | {_fmt(r.value)} ({r.reported}) | {_fmt(r.best)} | {_fmt(r.mean)} | "
                     f"{_fmt(r.std)} | {len(r.per_step)} | {_fmt(r.gain)} | {_fmt(r.still)} | "
                     f"{_fmt(r.arm.paper) if r.arm.paper is not None else '-'} | {_percent(max(r.torn))} | "
                     f"{sum(r.wall_time) / len(r.wall_time):.0f} |")
    return "\n".join(lines)


def plot(study: Study, rows: list[Row], path: Path) -> Path:
    """Ours (the reported value, one std over seeds, each seed a dot) beside the paper's number, per arm."""
    from codesign.plots import pyplot

    plt = pyplot()
    many = len(rows) > 8  # a grid's arms: narrower bars, labels turned upright
    fig, ax = plt.subplots(figsize=(1.6 + (0.45 if many else 1.3) * len(rows), 6.5 if many else 3.2),
                           constrained_layout=True)
    xs = range(len(rows))
    ax.bar([x - 0.2 for x in xs], [r.value for r in rows], width=0.4, yerr=[0 if math.isnan(r.std) else r.std
                                                                              for r in rows],
           capsize=3, label=f"ours ({study.scale} scale; {' or '.join(sorted({r.reported for r in rows}))} of seeds)")
    for x, r in zip(xs, rows):
        ax.scatter([x - 0.2] * len(r.per_step), r.per_step, color="k", s=8, zorder=3)
    ax.bar([x + 0.2 for x in xs], [r.arm.paper if r.arm.paper is not None else 0 for r in rows], width=0.4,
           label="paper", color="tab:gray")
    ax.axhline(0, color="k", linewidth=0.5)
    ax.set_xticks(list(xs), [r.arm.label for r in rows], fontsize=8, rotation=90 if many else 0)
    ax.set_ylabel("per-step return")
    ax.set_title(study.title, fontsize=9)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _analysis(ref: str) -> Callable[[Study, Path, bool], str]:
    """The analysis function named `module:function`."""
    module, _, function = ref.partition(":")
    try:
        return getattr(importlib.import_module(module), function)
    except (ImportError, AttributeError) as exc:
        raise RecipeError(f"invalid study: study.analysis: {ref!r} names no function ({exc}); "
                          f"give it as module:function, e.g. codesign_mpm.reports.analyses:loss_landscape") from exc


def _heading(study: Study) -> str:
    command = f"`codesign study {study.name}`" + ("" if study.scale == SCALE_DEFAULT else f" --scale {study.scale}")
    count = "" if study.analysis else f": {len(study.seeds)} seed{'s' if len(study.seeds) > 1 else ''} per arm"
    fewer = sorted({len(arm.seeds) for arm in study.arms if arm.seeds is not None and len(arm.seeds) < len(study.seeds)})
    if fewer and not study.analysis:
        count += f" ({' or '.join(map(str, fewer))} for the arms whose runs do not depend on the seed)"
    return f"## {study.title}\n\n{command}{count}. Paper: {study.paper}\n\n"


def _differs(study: Study) -> str:
    return f"\nWhat differs from the paper: {study.differs}\n" if study.differs else ""


def _data_line(study: Study) -> str:
    scale = "" if study.scale == SCALE_DEFAULT else f" --scale {study.scale}"
    data = data_path(study, Path(".")).relative_to(DOCS_PAGE.parent).as_posix()
    what = "one line per measured point" if study.analysis else "one line per run (every iteration's return)"
    return (f"Data: [{data}]({data}), {what}; `codesign study {study.name}{scale} --report --docs` rebuilds this "
            f"section from it.")


def section(study: Study, rows: list[Row]) -> str:
    reading = verdict(rows) + (f" {best_along(rows, *study.best_along)}" if study.best_along else "")
    parts = [table_markdown(rows), reading, f"![{study.name}]({study.name}.png)"]
    runs = sum(len(r.per_step) for r in rows)
    planned = sum(len(arm_seeds(study, arm)) for arm in study.arms)
    if runs < planned:
        parts.insert(0, f"**Under way**: {runs} of {planned} runs finished "
                        f"({len(rows)} of {len(study.arms)} arms have at least one).")
    parts.append(_data_line(study))
    body = "\n\n".join(parts)
    return _heading(study) + body + "\n" + _differs(study)


def records_for_report(study: Study, root: Path) -> list[dict]:
    """The records of the runs finished in `root`, and, for each arm with none there, the committed
    ones (docs/data/studies/): a fresh clone rebuilds the docs' tables from data alone, and a study
    too long for one machine's session goes on arm by arm (`--arm`) on the next without losing
    the arms it published. A no-action episode likewise (one played in an arm not run here)."""
    records = extract(study, root) if root.is_dir() else []
    committed = data_path(study)
    if not committed.is_file():
        return records
    by_arm = {arm.label: i for i, arm in enumerate(study.arms)}
    here = {r["arm"] for r in records if "best" in r}
    stills_here = {r["arm"] for r in records if "still" in r}
    adopted = [r for r in read_records(committed)[1]
               if r["arm"] in by_arm and r["arm"] not in (stills_here if "still" in r else here)]
    taken = sorted({r["arm"] for r in adopted if "best" in r})
    if taken:
        print(f"[{study.name}] {len(taken)} arm(s) with no finished run in {root}: reporting the committed "
              f"{committed} for them", file=sys.stderr, flush=True)
    return sorted(records + adopted, key=lambda r: by_arm[r["arm"]])


def write_results(study: Study, root: Path, records: list[dict] | None = None) -> list[Row]:
    """runs.jsonl, table.csv, table.md, the chart and section.md in the study's directory, from
    `records` (default: its finished runs')."""
    records = extract(study, root) if records is None else records
    rows = rows_from(study, records)
    root.mkdir(parents=True, exist_ok=True)
    write_records(study, records, root / RUNS_FILE)
    with open(root / "table.csv", "w", newline="", encoding="utf-8") as f:
        out = csv.writer(f)
        out.writerow(["arm", "reported", "value", "best", "mean", "std", "seeds", "gain", "paper", "per_step", "first",
                      "torn", "wall_time", "still"])
        for r in rows:
            out.writerow([r.arm.label, r.reported, r.value, r.best, r.mean, r.std, len(r.per_step), r.gain,
                          r.arm.paper, list(r.per_step), list(r.first), list(r.torn), list(r.wall_time), r.still])
    (root / "table.md").write_text(table_markdown(rows) + "\n", encoding="utf-8")
    plot(study, rows, root / f"{study.name}.png")
    (root / "section.md").write_text(section(study, rows), encoding="utf-8")
    return rows


def docs_links(text: str, charts: list[str]) -> str:
    """A section's chart links as docs/studies.md needs them (the charts go to docs/images/studies/)."""
    for chart in charts:
        text = text.replace(f"]({chart})", f"](images/studies/{chart})")
    return text


def publish(study: Study, root: Path, repo: Path = Path(".")) -> Path:
    """Put the study's section into docs/studies.md (replacing its earlier one), its chart into
    docs/images and its records into docs/data/studies/."""
    images = repo / DOCS_IMAGES
    images.mkdir(parents=True, exist_ok=True)
    charts = sorted(root.glob(f"{study.name}*.png"))  # the study's charts, as its section names them
    for chart in charts:
        shutil.copyfile(chart, images / chart.name)
    data = root / (POINTS_FILE if study.analysis else RUNS_FILE)
    if data.is_file():
        data_path(study, repo).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(data, data_path(study, repo))
    text = docs_links((root / "section.md").read_text(encoding="utf-8"), [c.name for c in charts])
    begin, end = f"<!-- study:{study.name} -->", f"<!-- /study:{study.name} -->"
    page = repo / DOCS_PAGE
    current = page.read_text(encoding="utf-8") if page.is_file() else "# The paper's studies\n"
    block = f"{begin}\n{text}{end}"
    pattern = re.compile(re.escape(begin) + ".*?" + re.escape(end), re.S)
    current = pattern.sub(lambda _: block, current) if pattern.search(current) else current.rstrip() + f"\n\n{block}\n"
    page.write_text(current, encoding="utf-8")
    return page


def published_section(page: Path, name: str) -> str | None:
    """The text of a study's section in docs/studies.md (None if it has none)."""
    found = re.search(re.escape(f"<!-- study:{name} -->") + "\n(.*?)" + re.escape(f"<!-- /study:{name} -->"),
                      page.read_text(encoding="utf-8"), re.S)
    return found.group(1) if found else None
