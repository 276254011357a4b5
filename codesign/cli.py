"""The ``codesign`` command line.

Core commands are ``run``, ``sweep``, ``eval``, ``show`` and ``plugins``; plugins add their own
through the ``codesign_cli`` hook. Plugins are loaded before the command line
is parsed (their commands must exist by then), so ``--disable-plugin`` is read
from the arguments ahead of time. Heavy modules are imported inside commands
only, to keep ``codesign --help`` fast.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from codesign.errors import CodesignError
from codesign.plugins import DISABLE_ENV, PluginManager, get_registry, load_plugins

_stderr = Console(stderr=True)


def build_app(plugin_manager: PluginManager) -> typer.Typer:
    """The typer app with the core commands and every plugin's commands."""
    app = typer.Typer(
        name="codesign",
        help="Co-design soft robots: run, inspect and extend recipes.",
        no_args_is_help=True,
        pretty_exceptions_enable=False,
        add_completion=False,
    )

    @app.callback()
    def _global_options(
        disable_plugin: Optional[list[str]] = typer.Option(  # noqa: ARG001 - applied before parsing
            None,
            "--disable-plugin",
            metavar="NAME",
            help=f"Do not load the plugin NAME (repeatable; also ${DISABLE_ENV}=a,b).",
        ),
    ) -> None:
        """Co-design soft robots: run, inspect and extend recipes."""

    @app.command()
    def run(
        recipe: Optional[str] = typer.Argument(None, help="Recipe file, or a name in recipes/."),
        overrides: Optional[list[str]] = typer.Argument(None, help="key=value overrides, e.g. seed=3."),
        run_dir: Optional[Path] = typer.Option(None, "--run-dir", help="Where to write the run."),
        resume: Optional[Path] = typer.Option(None, "--resume", help="Continue the run in this directory."),
        no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bar."),
    ) -> None:
        """Run a recipe (or resume a run) and print its run directory."""
        from codesign import runner

        if resume is not None:
            if recipe is not None or overrides or run_dir is not None:
                raise CodesignError("--resume takes no recipe, overrides or --run-dir: the run keeps its own")
            directory = runner.resume(resume, progress=not no_progress)
        else:
            if recipe is None:
                raise CodesignError("missing RECIPE (or --resume RUN_DIR)")
            from codesign.recipe import load_recipe

            resolved = load_recipe(recipe, overrides or [])
            directory = runner.run(resolved, run_dir=run_dir, progress=not no_progress)
        report = runner.progress_report(directory)
        if report:
            _stderr.print(report, markup=False, highlight=False, soft_wrap=True)
        typer.echo(str(directory))

    @app.command()
    def sweep(
        recipe: str = typer.Argument(..., help="Recipe file with a sweep: section, or a name in recipes/."),
        overrides: Optional[list[str]] = typer.Argument(None, help="key=value overrides, e.g. sweep.trials=4."),
        sweep_dir: Optional[Path] = typer.Option(None, "--sweep-dir", help="Where to write the sweep."),
        resume: bool = typer.Option(False, "--resume", help="Continue the sweep in --sweep-dir."),
        backend: Optional[str] = typer.Option(None, "--backend", help="local or ray (default: sweep.backend)."),
        ray_address: Optional[str] = typer.Option(
            None, "--ray-address", help="Ray cluster to join (default: $RAY_ADDRESS, else a local instance)."
        ),
        print_wandb_config: bool = typer.Option(
            False, "--print-wandb-config", help="Print the sweep as a W&B sweep config (`wandb sweep`); run nothing."
        ),
        no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bar."),
    ) -> None:
        """Run every configuration x seed of a recipe's sweep: section and print the sweep directory."""
        from codesign import sweep as sweeps
        from codesign.recipe import load_recipe

        resolved = load_recipe(recipe, overrides or [])
        if print_wandb_config:
            import yaml

            config = sweeps.wandb_sweep_config(resolved, recipe, overrides or [])
            typer.echo(yaml.safe_dump(config, sort_keys=False), nl=False)
            return
        if backend not in (None, "local", "ray"):
            raise CodesignError(f"--backend {backend!r}: choose from local, ray")
        directory = sweeps.run_sweep(resolved, sweep_dir=sweep_dir, resume=resume, backend=backend,
                                     ray_address=ray_address, progress=not no_progress)
        _stderr.print((directory / sweeps.SUMMARY_MD).read_text(encoding="utf-8"), markup=False, highlight=False,
                      soft_wrap=True)
        typer.echo(str(directory))

    @app.command()
    def study(
        name: str = typer.Argument(..., help="A study in recipes/studies/ (e.g. what_to_optimise), or a study file."),
        scale: str = typer.Option("cpu", "--scale", help="cpu (the default, reduced for a 2-core machine) or a "
                                                          "scale the study defines (tiny, paper)."),
        study_dir: Optional[Path] = typer.Option(None, "--dir", help="Where to write it (default studies/NAME, "
                                                                     "with -SCALE for other scales); continued if it exists."),
        docs: bool = typer.Option(False, "--docs", help="Also write its section into docs/studies.md and its chart "
                                                        "into docs/images/studies/."),
        report: bool = typer.Option(False, "--report", help="Run nothing: write the table of the runs finished so "
                                                            "far (a study under way, in --dir or its default) "
                                                            "and, for each arm with none there, of the records "
                                                            "committed in docs/data/studies/. An analysis reports "
                                                            "from its points (the committed ones where none are "
                                                            "here), measuring only those they lack."),
        backend: Optional[str] = typer.Option(None, "--backend", help="local (the default: one run after another) "
                                                                       "or ray (every arm's runs at once as Ray tasks)."),
        ray_address: Optional[str] = typer.Option(
            None, "--ray-address", help="Ray cluster to join (default: $RAY_ADDRESS, else a local instance)."
        ),
        arm: Optional[list[str]] = typer.Option(
            None, "--arm", help="Run only the arms whose label has this part (e.g. Diff-physics, 'Baby seal'; "
                                "repeatable: every one); the table holds every finished run (the committed ones "
                                "for arms not run here), a later run the rest."),
        no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bars."),
    ) -> None:
        """Run one of the paper's studies (every arm x seed, continuing a killed one) and print its table."""
        from codesign import study as studies

        spec = studies.load_study(name, scale)
        directory = studies.study_dir(spec, study_dir)
        if report and spec.analysis is None:
            studies.write_results(spec, directory, studies.records_for_report(spec, directory))
        else:  # an analysis reports by running: from the committed points (if none here), it measures nothing new
            if report and studies.seed_points(spec, directory):
                _stderr.print(f"reporting the committed {studies.data_path(spec)}", markup=False, highlight=False)
            directory = studies.run_study(spec, study_dir, progress=not no_progress, backend=backend,
                                          ray_address=ray_address, arms=arm or ())
        if docs:
            _stderr.print(f"wrote {studies.publish(spec, directory)}", markup=False, highlight=False)
        _stderr.print((directory / "section.md").read_text(encoding="utf-8"), markup=False, highlight=False,
                      soft_wrap=True)
        typer.echo(str(directory))

    @app.command("eval")
    def evaluate(
        run_dir: Path = typer.Argument(..., help="A run directory with a best/ design and controller."),
        overrides: Optional[list[str]] = typer.Argument(
            None, help="key=value changes to the run's recipe for the replay, e.g. environment.cfl=0.1 "
                       "(does the return hold at a quarter of the step?)."),
        episodes: int = typer.Option(1, "--episodes", min=1, help="Episodes to replay."),
    ) -> None:
        """Replay a run's best design and controller and print each episode's return and integrity.

        Integrity is printed where the environment measures it (torn-off mass, thinnest part)."""
        from codesign import runner
        from codesign.recipe import parse_overrides

        records = runner.replay_best(run_dir, episodes, parse_overrides(overrides) if overrides else None)
        for i, record in enumerate(records):
            typer.echo(episode_line(i, record.episode_return, record.metrics))
        returns = [record.episode_return for record in records]
        typer.echo(f"mean return {sum(returns) / len(returns):.6g} over {len(returns)} episode(s)")

    @app.command()
    def view(
        sources: list[Path] = typer.Argument(..., metavar="SOURCE", help="Run directories, sweep or study directories (each run's "
                                             "best), .npz exports of `codesign simulate --export`, designs "
                                             "(a run's best/design.npz) or annotated bodies (`codesign annotate`)."),
        iterations: str = typer.Option("best", "--iterations", help="Each run's episodes, comma-separated: best "
                                       "and/or 0 (the design and controller it started from), e.g. 0,best."),
        out: Optional[Path] = typer.Option(None, "--out", help="The recording, FILE.rrd (default: RUN_DIR/view.rrd, "
                                           "FILE.rrd beside a file, ./view.rrd for several sources)."),
        serve: bool = typer.Option(False, "--serve", help="Then serve it to a web browser on this machine "
                                   "(http://localhost:PORT) until Ctrl-C."),
        port: int = typer.Option(9090, "--port", min=1, max=65535, help="The web viewer's port with --serve."),
    ) -> None:
        """Write an interactive 3D recording of episodes or designs, print its path and how to open it."""
        wanted = [part.strip() for part in iterations.split(",") if part.strip()]
        if not wanted:
            raise CodesignError(f"--iterations {iterations!r}: name at least one of best, 0 (e.g. 0,best)")
        recording = plugin_manager.hook.codesign_view(sources=list(sources), iterations=wanted, out=out)
        if recording is None:
            raise CodesignError(f"no plugin can view {', '.join(map(str, sources))} (codesign_mpm views its own "
                                "environments' runs, exports and designs)")
        typer.echo(str(recording.path))
        _stderr.print(recording.how_to_open, markup=False, highlight=False, soft_wrap=True)
        if serve:
            recording.serve(port)

    @app.command()
    def show(
        recipe: str = typer.Argument(..., help="Recipe file, or a name in recipes/."),
        overrides: Optional[list[str]] = typer.Argument(None, help="key=value overrides, e.g. seed=3."),
    ) -> None:
        """Print the composed, validated recipe with every default filled in."""
        from codesign.recipe import load_recipe

        typer.echo(load_recipe(recipe, overrides or []).to_yaml(), nl=False)

    @app.command()
    def plugins(as_json: bool = typer.Option(False, "--json", help="Print a JSON list instead of a table.")) -> None:
        """List every registered component with its plugin and distribution."""
        rows = [
            {
                "kind": e.kind,
                "name": e.name,
                "plugin": e.plugin,
                "distribution": e.distribution,
                "description": e.description,
            }
            for e in get_registry().entries()
        ]
        if as_json:
            typer.echo(json.dumps(rows, indent=2))
            return
        table = Table("kind", "name", "plugin", "distribution", "description")
        for row in rows:
            table.add_row(*(str(row[k] or "-") for k in ("kind", "name", "plugin", "distribution", "description")))
        Console().print(table)

    plugin_manager.hook.codesign_cli(app=app)
    return app


def episode_line(i: int, episode_return: float, metrics: dict[str, float]) -> str:
    """`codesign eval`'s line for one replayed episode: its return, then the body's integrity figures
    that the environment reports (`codesign.artifacts.EPISODE_METRICS`), where it does."""
    line = f"episode {i}: return {episode_return:.6g}"
    if metrics.get("unplayable"):
        return line + " (the environment refused the design: not played)"
    if "torn_fraction" in metrics:
        line += f", torn off {100 * metrics['torn_fraction']:.3g}% of the robot's mass"
        if metrics.get("torn_at_frame"):
            line += f" (first over the tolerance at frame {metrics['torn_at_frame']:.0f})"
    if "thinnest_cells" in metrics:
        line += f", thinnest part {metrics['thinnest_cells']:.3g} cells"
    return line


def _disabled_plugins(argv: list[str]) -> list[str]:
    """Values of ``--disable-plugin NAME`` / ``--disable-plugin=NAME`` in ``argv``."""
    names = []
    for i, arg in enumerate(argv):
        if arg == "--disable-plugin" and i + 1 < len(argv):
            names.append(argv[i + 1])
        elif arg.startswith("--disable-plugin="):
            names.append(arg.split("=", 1)[1])
    return names


def main(argv: list[str] | None = None) -> None:
    """Console entry point: user errors print one red line and exit 1, bugs show a traceback."""
    args = sys.argv[1:] if argv is None else argv
    # standard output carries a command's result (`dir=$(codesign run ...)`): no Taichi banner on it;
    # summary.json records Taichi's version, and a user's own setting wins
    os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")
    try:
        app = build_app(load_plugins(_disabled_plugins(args)))
        app(args=args, prog_name="codesign")
    except CodesignError as exc:
        _stderr.print(f"error: {exc}", style="red", markup=False, highlight=False, soft_wrap=True)
        raise SystemExit(1) from None
