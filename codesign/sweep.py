"""Sweeps without a server: a recipe's ``sweep:`` section turned into runs, proposed by Optuna.

The section has W&B's sweep-config form (``method``, ``metric``, ``parameters`` over dotted
recipe keys); ``seed`` among the parameters is not searched but replicated: every configuration
(the values of all other parameters) runs once per seed, and the summary aggregates over seeds.
One Optuna trial is one configuration; its value is the metric's mean over its seeds.

A sweep directory holds:

- ``sweep.yaml``: the resolved recipe, sweep section included (a resumed sweep must match it, read
  with today's defaults for fields added since);
- ``optuna.journal``: Optuna's study (a JournalFileBackend: a plain file, no database server);
- ``t<trial>-seed<seed>/``: one ordinary run directory per configuration and seed;
- ``summary.csv``, ``summary.md``: the metric's mean, std and n over seeds per configuration;
- ``learning_curves.png``: the metric against iteration, mean and spread over seeds.

Resume (``--resume``): finished runs (``summary.json`` with status ``completed``) are skipped,
a run that has a ``config.yaml`` is continued with :func:`codesign.runner.resume`, and the
configurations that the killed sweep had proposed but not finished are completed before any new
one is proposed. See docs/sweeps.md.
"""
from __future__ import annotations

import csv
import dataclasses
import itertools
import json
import math
import os
import shutil
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import OmegaConf

from codesign.errors import CodesignError, RecipeError
from codesign.recipe import ResolvedRecipe, SweepConfig, merge_recipes, resolve_recipe
from codesign.registry import suggest
from codesign.runner import CONFIG_FILE, METRICS_FILE, SUMMARY_FILE, fresh_dir, read_metrics
from codesign.tracking import WandbTracker, wandb_off

if TYPE_CHECKING:
    import optuna

SWEEP_FILE = "sweep.yaml"
JOURNAL_FILE = "optuna.journal"
SUMMARY_CSV = "summary.csv"
SUMMARY_MD = "summary.md"
CURVES_FILE = "learning_curves.png"
SEED = "seed"
DISTRIBUTIONS = ("uniform", "log_uniform_values", "int_uniform")
_SPEC_KEYS = ("value", "values", "distribution", "min", "max")
_NOT_SWEPT = ("name", "run_dir", "sweep")  # the sweep sets these itself


@dataclass(frozen=True)
class Dimension:
    """One swept recipe key: discrete ``values`` or a ``distribution`` between ``low`` and ``high``."""

    key: str
    values: tuple[Any, ...] = ()
    distribution: str | None = None
    low: float = 0.0
    high: float = 0.0

    def optuna_distribution(self) -> optuna.distributions.BaseDistribution:
        """Discrete values are searched by index, so any YAML value (a list, a mapping) can be one."""
        from optuna.distributions import CategoricalDistribution, FloatDistribution, IntDistribution

        if self.distribution is None:
            return CategoricalDistribution(list(range(len(self.values))))
        if self.distribution == "int_uniform":
            return IntDistribution(int(self.low), int(self.high))
        return FloatDistribution(self.low, self.high, log=self.distribution == "log_uniform_values")

    def value(self, sampled: Any) -> Any:
        return self.values[sampled] if self.distribution is None else sampled


@dataclass(frozen=True)
class Plan:
    """A validated sweep: the base recipe data, what is searched, over which seeds."""

    name: str
    config: SweepConfig
    base: dict
    dimensions: tuple[Dimension, ...]
    seeds: tuple[int, ...]

    @property
    def grid_size(self) -> int:
        return math.prod(len(d.values) for d in self.dimensions)

    @property
    def configurations(self) -> int:
        """How many configurations the sweep tries: the whole grid (or `trials` of it), else `trials`."""
        if self.config.method == "grid":
            return min(self.grid_size, self.config.trials or self.grid_size)
        assert self.config.trials is not None
        return self.config.trials

    def configuration(self, params: Mapping[str, Any]) -> dict[str, Any]:
        """Recipe key -> value of an Optuna trial's parameters."""
        return {d.key: d.value(params[d.key]) for d in self.dimensions}

    def run_data(self, configuration: Mapping[str, Any], seed: int, run_dir: Path) -> dict:
        """The recipe of one run: the base with the configuration and seed applied, in the sweep's W&B group."""
        data = _apply(self.base, {**configuration, SEED: seed})
        tracking = {**data["tracking"], "wandb": data["tracking"]["wandb_mode"] != "disabled", "group": self.name}
        return {**data, "name": f"{self.name}-{run_dir.name}", "run_dir": str(run_dir), "tracking": tracking}


def plan_sweep(recipe: ResolvedRecipe) -> Plan:
    """Check the sweep section against the recipe before anything runs; every problem at once."""
    config = recipe.settings.sweep
    if config is None:
        raise RecipeError(f"invalid recipe '{recipe.name}': sweep: missing; a sweep needs a 'sweep:' section "
                          f"(method, metric, parameters; see docs/sweeps.md)")
    base = {**recipe.data, "sweep": None}
    problems: list[str] = []
    dimensions, seeds = [], (recipe.seed,)
    if not config.parameters:
        problems.append("sweep.parameters: empty; give at least one dotted recipe key, e.g. seed: {values: [0, 1]}")
    for key, spec in config.parameters.items():
        dimension = _dimension(key, spec, base, config.method, problems)
        if dimension is None:
            continue
        if key == SEED:
            seeds = dimension.values
        else:
            dimensions.append(dimension)
    if config.method != "grid" and config.trials is None:
        problems.append(f"sweep.trials: missing; method {config.method} needs the number of configurations to try")
    if not problems:
        problems += _probe(recipe.name, base, dimensions, seeds, config.method)
    if problems:
        raise RecipeError(f"invalid recipe '{recipe.name}': " + "\n  ".join(problems))
    return Plan(recipe.name, config, base, tuple(dimensions), tuple(seeds))


def _dimension(key: str, spec: Any, base: dict, method: str, problems: list[str]) -> Dimension | None:
    path = f"sweep.parameters.{key}"
    before = len(problems)
    _check_key(key, base, path, problems)
    if not isinstance(spec, Mapping):
        problems.append(f"{path}: {spec!r} is not a mapping; allowed: {{values: [...]}}, {{value: x}}, "
                        f"{{distribution: {'|'.join(DISTRIBUTIONS)}, min: a, max: b}}")
        return None
    unknown = [k for k in spec if k not in _SPEC_KEYS]
    if unknown:
        problems.append(f"{path}.{unknown[0]}: unknown key; {suggest(str(unknown[0]), _SPEC_KEYS)}"
                        f"allowed: {', '.join(_SPEC_KEYS)}")
    if "value" in spec or "values" in spec:
        if "value" in spec and "values" in spec or {"distribution", "min", "max"} & spec.keys():
            problems.append(f"{path}: give one of value, values or distribution/min/max, not several")
        values = [spec["value"]] if "value" in spec else spec["values"]
        if not isinstance(values, list) or not values:
            problems.append(f"{path}.values: {values!r} is empty or not a list; allowed: a non-empty list")
        elif key == SEED and not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in values):
            problems.append(f"{path}.values: {values!r}; allowed: seeds, integers >= 0")
        elif key == SEED and len(set(values)) != len(values):
            problems.append(f"{path}.values: {values!r} repeats a seed; allowed: distinct seeds")
        return Dimension(key, tuple(values)) if len(problems) == before else None
    if key == SEED:
        problems.append(f"{path}: seeds are replicates, not searched; allowed: values or value")
        return None
    if method == "grid":
        problems.append(f"{path}: a grid needs discrete values; allowed: values or value "
                        f"(distributions are for random and bayes)")
        return None
    low, high = spec.get("min"), spec.get("max")
    numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (low, high))
    if not numbers:
        problems.append(f"{path}: min {low!r}, max {high!r}; allowed: numbers (or values / value)")
        return None
    distribution = spec.get("distribution", "int_uniform" if isinstance(low, int) and isinstance(high, int)
                            else "uniform")  # W&B's inference
    if distribution not in DISTRIBUTIONS:
        problems.append(f"{path}.distribution: {distribution!r} is not supported; "
                        f"{suggest(str(distribution), DISTRIBUTIONS)}allowed: {', '.join(DISTRIBUTIONS)}")
    elif not low < high:
        problems.append(f"{path}: min {low!r} is not below max {high!r}; allowed: min < max")
    elif distribution == "log_uniform_values" and low <= 0:
        problems.append(f"{path}: min {low!r}; allowed: min > 0 for log_uniform_values")
    elif distribution == "int_uniform" and not (isinstance(low, int) and isinstance(high, int)):
        problems.append(f"{path}: min {low!r}, max {high!r}; allowed: integers for int_uniform")
    if len(problems) > before:
        return None
    return Dimension(key, (), distribution, low, high)


def _check_key(key: str, base: dict, path: str, problems: list[str]) -> None:
    """The key must name a setting of the recipe as resolved (defaults filled in: `codesign show`)."""
    if key.split(".")[0] in _NOT_SWEPT:
        problems.append(f"{path}: {key!r} is set by the sweep itself; allowed: any other recipe key")
        return
    node: Any = base
    for depth, part in enumerate(parts := key.split(".")):
        if not isinstance(node, Mapping) or part not in node:
            where = ".".join(parts[:depth])
            known = sorted(f"{where}.{k}" if where else str(k) for k in node) if isinstance(node, Mapping) else []
            hint = suggest(key, known) if known else ""
            problems.append(f"{path}: {key!r} is not a recipe key; {hint}allowed: {', '.join(known) or '(none)'}")
            return
        node = node[part]


def _probe(name: str, base: dict, dimensions: list[Dimension], seeds: tuple[int, ...], method: str) -> list[str]:
    """Resolve the recipes the sweep will run (a grid: all of them; otherwise each value and bound
    alone), so a bad value fails now and not after hours of other trials."""
    if method == "grid":
        combos = [dict(zip([d.key for d in dimensions], values))
                  for values in itertools.product(*(d.values for d in dimensions))]
    else:
        combos = [{d.key: v} for d in dimensions for v in (d.values or (d.low, d.high))]
    problems: list[str] = []
    for combo in combos or [{}]:
        for seed in seeds:
            try:
                resolve_recipe(_apply(base, {**combo, SEED: seed}))
            except RecipeError as exc:
                setting = ", ".join(f"{k}={v!r}" for k, v in {**combo, SEED: seed}.items())
                problems.append(f"sweep.parameters: the run with {setting} is invalid: "
                                f"{str(exc).split(': ', 1)[-1]}")
                return problems  # one is enough to see what is wrong
    return problems


def _apply(data: dict, values: Mapping[str, Any]) -> dict:
    """`data` with each dotted key set to its value, merged as a `key=value` override would be."""
    for key, value in values.items():
        for part in reversed(key.split(".")):
            value = {part: value}
        data = merge_recipes(data, value)
    return data


# --- running ------------------------------------------------------------------------------------


def execute(data: dict, progress: bool = False) -> str:
    """Run the recipe `data` in ``data['run_dir']`` (also as a Ray task): continue a run that was
    started (it has a config.yaml), else start it afresh; return the run directory."""
    from codesign import runner

    run_dir = Path(data["run_dir"])
    if (run_dir / CONFIG_FILE).is_file():
        runner.resume(run_dir, progress=progress)
    else:
        if run_dir.exists():
            shutil.rmtree(run_dir)  # created, but killed before it held anything to continue from
        runner.run(resolve_recipe(data), run_dir=run_dir, progress=progress)
    return str(run_dir)


def finished(run_dir: Path) -> bool:
    """A run is finished when its summary says it completed."""
    summary = run_dir / SUMMARY_FILE
    return summary.is_file() and json.loads(summary.read_text(encoding="utf-8")).get("status") == "completed"


def metric_value(run_dir: Path, metric: str) -> float:
    """The sweep metric (a dotted key of summary.json, e.g. best.episode_return) of a finished run."""
    node: Any = json.loads((run_dir / SUMMARY_FILE).read_text(encoding="utf-8"))
    for part in metric.split("."):
        if not isinstance(node, Mapping) or part not in node:
            known = ", ".join(node) if isinstance(node, Mapping) else "(none)"
            raise CodesignError(f"sweep.metric.name: {metric!r} is not in {run_dir / SUMMARY_FILE}; "
                                f"found {known} at '{part}'")
        node = node[part]
    return float(node)


class LocalExecutor:
    """Runs one run at a time in this process, when waited on."""

    slots = 1

    def __init__(self) -> None:
        self._queue: list[tuple[Any, dict]] = []

    def submit(self, key: Any, data: dict) -> None:
        self._queue.append((key, data))

    def pending(self) -> int:
        return len(self._queue)

    def wait(self) -> tuple[Any, BaseException | None]:
        key, data = self._queue.pop(0)
        try:
            execute(data)
        except Exception as exc:  # recorded; the sweep stops once the runs under way are done
            return key, exc
        return key, None


def connect_ray(address: str | None) -> Any:
    """Ray, joined to the cluster at `address` (None: ``RAY_ADDRESS``, else a local instance); an
    already initialised Ray (a Ray worker's, or a test's) is used as it is. Started here, the job's
    workers get this process's ``CODESIGN_*`` and ``WANDB_*`` variables (which plugins load, W&B's
    mode and directories), which workers on other nodes would not inherit."""
    try:
        import ray
    except ImportError:
        raise CodesignError("the ray backend needs Ray: pip install 'codesign[ray]'") from None
    if not ray.is_initialized():
        env_vars = {k: v for k, v in os.environ.items() if k.startswith(("CODESIGN_", "WANDB_"))}
        ray.init(address=address, runtime_env={"env_vars": env_vars})
    return ray


def run_task(ray: Any, function: Callable[..., Any] = execute) -> Any:
    """`execute` (or `function`, which runs one recipe as it does) as a Ray task: one CPU, and one
    GPU where the cluster has GPUs (the run's recipe chooses its device: `arch: cuda` uses the GPU
    Ray gives it)."""
    gpus = 1 if ray.cluster_resources().get("GPU", 0) >= 1 else 0
    return ray.remote(num_cpus=1, num_gpus=gpus)(function)


class RayExecutor:
    """Runs each run as a Ray task (`run_task`) on the cluster at `address` (see `connect_ray`). The
    sweep directory must be on a filesystem that every node sees (run directories are written there)."""

    def __init__(self, address: str | None) -> None:
        ray = connect_ray(address)
        self._ray = ray
        self._task = run_task(ray)
        resources = ray.cluster_resources()
        self.slots = max(1, int(resources.get("GPU") or resources.get("CPU", 1)))
        self._refs: dict[Any, Any] = {}

    def submit(self, key: Any, data: dict) -> None:
        self._refs[self._task.remote(data)] = key

    def pending(self) -> int:
        return len(self._refs)

    def wait(self) -> tuple[Any, BaseException | None]:
        (ref,), _ = self._ray.wait(list(self._refs), num_returns=1)
        key = self._refs.pop(ref)
        try:
            self._ray.get(ref)
        except Exception as exc:
            return key, exc
        return key, None


def run_sweep(recipe: ResolvedRecipe, *, sweep_dir: str | Path | None = None, resume: bool = False,
              backend: str | None = None, ray_address: str | None = None, progress: bool = True) -> Path:
    """Run (or, with `resume`, continue) the recipe's sweep; return the sweep directory."""
    plan = plan_sweep(recipe)
    directory = _sweep_dir(recipe, sweep_dir, resume)
    study = _study(plan, directory)
    executor = RayExecutor(ray_address) if (backend or plan.config.backend) == "ray" else LocalExecutor()
    _loop(plan, directory, study, executor, progress)
    write_summary(plan, directory, study)
    return directory


def _sweep_dir(recipe: ResolvedRecipe, sweep_dir: str | Path | None, resume: bool) -> Path:
    stored = OmegaConf.to_yaml(OmegaConf.create(_comparable(recipe.data)))
    if resume:
        if sweep_dir is None:
            raise CodesignError("--resume needs --sweep-dir: the sweep directory to continue")
        directory = Path(sweep_dir)
        if not (directory / SWEEP_FILE).is_file():
            raise CodesignError(f"{directory} is not a sweep directory (no {SWEEP_FILE})")
        if not _same_recipe((directory / SWEEP_FILE).read_text(encoding="utf-8"), stored):
            raise CodesignError(f"the recipe differs from the one the sweep in {directory} ran ({SWEEP_FILE}); "
                                f"resume with the same recipe and overrides (only sweep.backend may change)")
        return directory
    directory = Path(sweep_dir) if sweep_dir is not None else fresh_dir("sweeps", recipe.name)
    if directory.exists() and any(directory.iterdir()):
        raise CodesignError(f"sweep directory {directory} is not empty; continue it with --resume "
                            f"--sweep-dir {directory} or choose another --sweep-dir")
    directory.mkdir(parents=True, exist_ok=True)
    (directory / SWEEP_FILE).write_text(stored, encoding="utf-8")
    return directory


def _same_recipe(ran: str, stored: str) -> bool:
    """Whether the recipe a sweep ran (its sweep.yaml) is `stored` (this one, as it would be stored).
    The old file is read again with today's schemas if the text differs: a field added since then
    takes its default, which keeps the behaviour from before it, so the sweep still resumes."""
    if ran == stored:
        return True
    try:
        again = resolve_recipe(OmegaConf.to_container(OmegaConf.create(ran)))
    except (RecipeError, ValueError):
        return False
    return OmegaConf.to_yaml(OmegaConf.create(_comparable(again.data))) == stored


def _comparable(data: dict) -> dict:
    """The recipe as a resumed sweep must match it: where trials run may change."""
    return {**data, "sweep": {k: v for k, v in data["sweep"].items() if k != "backend"}}


def _study(plan: Plan, directory: Path) -> optuna.Study:
    import optuna
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    seed = plan.config.seed
    if plan.config.method == "grid":
        space = {d.key: list(range(len(d.values))) for d in plan.dimensions}
        sampler: optuna.samplers.BaseSampler = _grid_sampler(space, seed)
    elif plan.config.method == "random":
        sampler = optuna.samplers.RandomSampler(seed=seed)
    else:
        sampler = optuna.samplers.TPESampler(seed=seed)
    storage = JournalStorage(JournalFileBackend(str(directory / JOURNAL_FILE)))
    return optuna.create_study(study_name=plan.name, storage=storage, sampler=sampler, load_if_exists=True,
                               direction=plan.config.metric.goal)


def _grid_sampler(space: dict[str, list[int]], seed: int) -> optuna.samplers.BaseSampler:
    """Optuna's GridSampler, minus stopping the study once the grid is done: that works only inside
    `Study.optimize` and raises under ask-and-tell; the sweep counts configurations itself."""
    import optuna

    class AskTellGridSampler(optuna.samplers.GridSampler):
        def after_trial(self, study: optuna.Study, trial: Any, state: Any, values: Any) -> None:
            pass

    return AskTellGridSampler(space, seed=seed)


def run_dir_of(directory: Path, trial: int, seed: int) -> Path:
    return directory / f"t{trial:03d}-seed{seed}"


def _loop(plan: Plan, directory: Path, study: optuna.Study, executor: LocalExecutor | RayExecutor,
          progress: bool) -> None:
    """Keep the executor's slots busy: first the configurations a killed sweep left unfinished,
    then new ones from the sampler; a configuration's value is told once all its seeds finished."""
    from optuna.trial import TrialState

    from codesign.progress import progress_bar

    trials = study.get_trials(deepcopy=False)
    unfinished = [(t.number, t.params) for t in trials if t.state == TrialState.RUNNING]
    done = sum(t.state == TrialState.COMPLETE for t in trials)
    proposed = len(trials)
    waiting: dict[int, set[int]] = {}  # trial -> seeds still running
    errors: list[str] = []
    with progress_bar(total=plan.configurations * len(plan.seeds), initial=done * len(plan.seeds),
                      desc=f"sweep {plan.name}", unit="run", show=progress) as bar:

        def start(number: int, params: dict) -> None:
            configuration = plan.configuration(params)
            waiting[number] = set()
            for seed in plan.seeds:
                run_dir = run_dir_of(directory, number, seed)
                if finished(run_dir):
                    bar.update(1)
                else:
                    waiting[number].add(seed)
                    executor.submit((number, seed), plan.run_data(configuration, seed, run_dir))
            if not waiting[number]:
                tell(number)

        def tell(number: int) -> None:
            del waiting[number]
            values = [metric_value(run_dir_of(directory, number, s), plan.config.metric.name) for s in plan.seeds]
            study.tell(number, sum(values) / len(values))

        while True:
            while executor.pending() < executor.slots and not errors:
                if unfinished:
                    start(*unfinished.pop(0))
                elif proposed < plan.configurations:
                    trial = study.ask({d.key: d.optuna_distribution() for d in plan.dimensions})
                    proposed += 1
                    start(trial.number, trial.params)
                else:
                    break
            if not executor.pending():
                break
            (number, seed), error = executor.wait()
            if error is not None:
                errors.append(f"{run_dir_of(directory, number, seed)}: {type(error).__name__}: {error}")
                continue
            bar.update(1)
            waiting[number].discard(seed)
            if not waiting[number]:
                tell(number)
    if errors:
        write_summary(plan, directory, study)
        raise CodesignError(f"{len(errors)} run(s) of the sweep failed (the finished ones are kept; fix the "
                            f"cause and continue with --resume --sweep-dir {directory}):\n  " + "\n  ".join(errors))


# --- summary ------------------------------------------------------------------------------------


def _configurations(plan: Plan, directory: Path, study: optuna.Study) -> Iterator[tuple[dict, list[Path]]]:
    """(configuration, its run directories) of every configuration whose runs all finished."""
    from optuna.trial import TrialState

    for trial in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
        yield plan.configuration(trial.params), [run_dir_of(directory, trial.number, s) for s in plan.seeds]


def summary_rows(plan: Plan, directory: Path, study: optuna.Study) -> list[dict[str, Any]]:
    """One row per finished configuration: its values, then mean, std (n - 1) and n of the metric
    over seeds; best first."""
    rows = []
    for configuration, run_dirs in _configurations(plan, directory, study):
        values = [metric_value(d, plan.config.metric.name) for d in run_dirs]
        n, mean = len(values), sum(values) / len(values)
        std = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1)) if n > 1 else math.nan
        rows.append({**{k: _cell(v) for k, v in configuration.items()}, "mean": mean, "std": std, "n": n})
    rows.sort(key=lambda r: r["mean"], reverse=plan.config.metric.goal == "maximize")
    return rows


def _cell(value: Any) -> Any:
    return value if isinstance(value, (int, float, str, bool)) or value is None else json.dumps(value)


def write_summary(plan: Plan, directory: Path, study: optuna.Study) -> None:
    """summary.csv, summary.md and learning_curves.png in the sweep directory; the plot and the
    table go to W&B too, as a run of the sweep's group, unless W&B is disabled."""
    from codesign.plots import sweep_curves

    rows = summary_rows(plan, directory, study)
    columns = [d.key for d in plan.dimensions] + ["mean", "std", "n"]
    with (directory / SUMMARY_CSV).open("w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, columns)
        writer.writeheader()
        writer.writerows(rows)
    (directory / SUMMARY_MD).write_text(summary_markdown(plan, rows, columns), encoding="utf-8")
    metric = plan.config.metric.name.split(".")[-1]
    curves = {_label(c): [read_metrics(d / METRICS_FILE) for d in run_dirs]
              for c, run_dirs in _configurations(plan, directory, study)}
    plot = sweep_curves(curves, directory / CURVES_FILE, f"sweep {plan.name}", metric)
    tracking = plan.base["tracking"]
    if not wandb_off(tracking["wandb_mode"]):
        tracker = WandbTracker(directory, mode=tracking["wandb_mode"], project=tracking["project"], group=plan.name,
                               name=f"{plan.name}-summary", config={"sweep": dataclasses.asdict(plan.config)},
                               job_type="sweep-summary")
        if plot is not None:
            tracker.log_image("learning_curves", plot)
        tracker.log_table("summary", columns, [[r[c] for c in columns] for r in rows])
        tracker.close()


def summary_markdown(plan: Plan, rows: list[dict], columns: list[str]) -> str:
    metric = plan.config.metric
    lines = [f"# Sweep {plan.name}", "",
             f"{metric.name} ({metric.goal}), mean and std over seeds {list(plan.seeds)}; best first.", "",
             "| " + " | ".join(columns) + " |", "|" + " --- |" * len(columns)]
    for row in rows:
        lines.append("| " + " | ".join(_format(row[c]) for c in columns) + " |")
    return "\n".join(lines) + "\n"


def _format(value: Any) -> str:
    if isinstance(value, float):
        return "-" if math.isnan(value) else f"{value:.6g}"
    return str(value)


def _label(configuration: Mapping[str, Any]) -> str:
    return ", ".join(f"{k.split('.')[-1]}={_cell(v)}" for k, v in configuration.items()) or "base"


# --- W&B online ---------------------------------------------------------------------------------


def wandb_sweep_config(recipe: ResolvedRecipe, recipe_ref: str, overrides: list[str]) -> dict[str, Any]:
    """The same sweep as a native W&B sweep (``wandb sweep FILE``, then ``wandb agent ID``): W&B's
    controller proposes, each agent runs ``codesign run RECIPE overrides key=value...`` online.
    There the seed is an ordinary parameter; group the runs by configuration in W&B's UI."""
    plan = plan_sweep(recipe)
    config: dict[str, Any] = {
        "name": plan.name,
        "program": recipe_ref,
        "method": plan.config.method,
        "metric": {"name": plan.config.metric.name, "goal": plan.config.metric.goal},
        "parameters": recipe.data["sweep"]["parameters"],
        "command": ["codesign", "run", "${program}", *overrides, "tracking.wandb=true", "tracking.wandb_mode=online",
                    "--no-progress", "${args_no_hyphens}"],
    }
    if plan.config.trials is not None:
        config["run_cap"] = plan.configurations * len(plan.seeds)
    return config
