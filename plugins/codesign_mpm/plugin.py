"""Registers the MPM environments and the `simulate` command; imports nothing heavy.

Each entry of `codesign_mpm.environment.config.PRESETS` becomes an environment of the same name; another
plugin adds its own with `register_environment`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Optional

from codesign.hookspecs import hookimpl
from codesign.registry import PluginRegistrar
from codesign_mpm.environment.config import PRESET_CONFIGS, PRESETS, EnvironmentPreset, LocomotionConfig, preset_config

if TYPE_CHECKING:
    import typer

    from codesign.hookspecs import ViewRecording

    from codesign_mpm.environment.env import LocomotionEnv


@dataclass(frozen=True)
class PresetEnvironment:
    """Factory for one preset; imports the engine only when a recipe builds the environment."""

    preset: EnvironmentPreset

    def __call__(self, config: LocomotionConfig) -> LocomotionEnv:
        from codesign_mpm.environment.env import LocomotionEnv

        return LocomotionEnv(config, self.preset)


def register_environment(registry: PluginRegistrar, name: str, preset: EnvironmentPreset) -> None:
    """Add an MPM locomotion environment `name`: the engine's scene (terrain, robot, task) with the
    preset's terrain friction, cover and robot stiffness as its defaults. Call it from a plugin's
    `codesign_register`; `codesign render`, `view` and `eval` take its runs as the built-in ones'."""
    config = PRESET_CONFIGS[name] if PRESETS.get(name) is preset else preset_config(name, preset)  # built-ins: made once
    registry.add("environment", name, PresetEnvironment(preset), config, preset.description)


def is_mpm_environment(name: str) -> bool:
    """Whether the registered environment `name` is one of this engine's (built-in or added by
    `register_environment`)."""
    from codesign.plugins import get_registry
    from codesign.registry import RegistryError

    try:
        return isinstance(get_registry().get("environment", name).load_factory(), PresetEnvironment)
    except RegistryError:  # a plugin's environment that is no longer installed
        return False


@hookimpl
def codesign_register(registry: PluginRegistrar) -> None:
    for name, preset in PRESETS.items():
        register_environment(registry, name, preset)


@hookimpl
def codesign_register_materials() -> list[str]:
    """The engine's own material models, listed like a plugin's (`codesign plugins`)."""
    from codesign_mpm.materials import BUILTIN

    return [f"codesign_mpm.materials.{name}" for name in BUILTIN]


@hookimpl
def codesign_render_run(run_dir: Path, camera: str, fps: int, progress: bool) -> Path | None:
    """`render.enabled: true` in a recipe: its best episode to best/episode.mp4 (MPM environments only)."""
    from codesign.runner import load_run_data

    _, recipe = load_run_data(run_dir)
    if not is_mpm_environment(recipe.sections["environment"].name):
        return None
    from codesign_mpm.viewing.render import render as render_files

    return render_files(run_dir, camera=camera, fps=fps, progress=progress)[0]


@hookimpl
def codesign_view(sources: list[Path], iterations: list[str], out: Path | None) -> ViewRecording | None:
    """`codesign view`: MPM runs (their environment a preset here), sweeps or studies of them, exports
    of `codesign simulate` and designs, as a Rerun recording (codesign_mpm.viewing.view)."""
    from codesign.runner import load_run_data
    from codesign_mpm.viewing.view import is_run, runs_under, view

    for source in sources:
        runs = ([source] if is_run(source) else runs_under(source)) if source.is_dir() else []
        for run in runs:
            if not is_mpm_environment(load_run_data(run)[1].sections["environment"].name):
                return None
    return view(sources, iterations, out)


@hookimpl
def codesign_cli(app: typer.Typer) -> None:
    import json

    import typer  # already loaded by the CLI

    def _echo_json(record: dict) -> None:
        typer.echo(json.dumps(record))

    def _measure_or_read(measure, from_file: Optional[Path], report: Optional[Path], write_report) -> None:
        """Measure (printing JSON lines), or read earlier lines from `from_file`; then write the report."""
        if from_file is not None:
            rows = [json.loads(line) for line in from_file.read_text().splitlines() if line.strip()]
        else:
            rows = measure()
        if report is not None:
            typer.echo(str(write_report(rows, report)))

    @app.command()
    def simulate(
        scene: Path = typer.Argument(..., help="Scene YAML (keys of codesign_mpm.scene.spec.Scene)."),
        frames: int = typer.Option(100, "--frames", min=0, help="Frames (control steps) to simulate."),
        export: Optional[Path] = typer.Option(
            None, "--export", help="Write per-frame x, v (frames+1, N, 3) and material, body, frame_dt to .npz."
        ),
        no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bar."),
    ) -> None:
        """Simulate a scene file headless (zero actions) and print a performance summary."""
        from codesign_mpm.simulate import load_scene
        from codesign_mpm.simulate import simulate as run_scene

        loaded = load_scene(scene)
        report = run_scene(loaded, frames, export=export, progress=not no_progress)
        typer.echo(f"particles               {report.particles}")
        typer.echo(f"grid                    {' x '.join(map(str, report.grid))} (dx {loaded.dx:.4g})")
        typer.echo(f"substeps per frame      {report.substeps} (dt {report.dt:.4g} s)")
        typer.echo(f"frames                  {report.frames} of {loaded.frame_dt:.4g} s")
        typer.echo(f"setup time              {report.build_time:.2f} s")
        typer.echo(f"wall time               {report.wall_time:.2f} s "
                   f"(first frame {report.first_frame_time:.2f} s: kernel compile or cache load)")
        typer.echo(f"particle-substeps / s   {report.particle_substeps_per_second:.3g} (after the first frame)")
        if export is not None:
            typer.echo(f"exported                {export}")

    @app.command()
    def render(
        source: Path = typer.Argument(..., help="A run directory (its best design and controller are replayed "
                                      "for one episode) or an .npz from `codesign simulate --export`."),
        out: Optional[Path] = typer.Option(None, "--out", help="Video, .mp4 or .gif (default: RUN_DIR/best/"
                                           "episode.mp4, or the .npz's name with .mp4; none if only --still)."),
        still: Optional[Path] = typer.Option(None, "--still", help="Also (or only) a .png of the design at rest, "
                                             "coloured by muscle group."),
        camera: str = typer.Option("oblique", "--camera", help="side, top or oblique."),
        fps: int = typer.Option(25, "--fps", min=1, help="Frames per second of the video."),
        no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bar."),
    ) -> None:
        """Render an episode headless to a video (robot red/blue by muscle activation) and/or a still."""
        from codesign_mpm.viewing.render import CAMERAS
        from codesign_mpm.viewing.render import render as render_files

        if camera not in CAMERAS:
            raise typer.BadParameter(f"--camera {camera!r}: choose from {', '.join(CAMERAS)}")
        for path in render_files(source, out, still, camera, fps, progress=not no_progress):
            typer.echo(str(path))

    bench = typer.Typer(help="Benchmarks that print JSON lines to compare run to run.", no_args_is_help=True)
    app.add_typer(bench, name="bench")

    def _check_arch(arch: str) -> None:
        if arch not in ("cpu", "cuda"):
            raise typer.BadParameter(f"--arch {arch!r}: choose from cpu, cuda")

    @bench.command("environments")
    def bench_environments(
        scale: list[str] = typer.Option(["small"], "--scale", help="small (dx 1/64, a cover sized for about 18k "
                                        "particles in all) and/or paper (dx 1/128, for about 145k; ground and ice, "
                                        "without a cover, 61k; the ocean's water covers the robot: about 190k); "
                                        "repeatable."),
        env: list[str] = typer.Option(list(PRESETS), "--env", help="Environment preset(s); repeatable."),
        arch: str = typer.Option("cpu", "--arch", help="cpu or cuda."),
        no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bar."),
    ) -> None:
        """Forward throughput of one scene per environment: particle-substeps/s, substeps per
        control step and ms per substep (the old code, paper scale: about 245 ms, 41 substeps)."""
        from codesign_mpm.reports.bench import ENV_SCALES, run_environment_bench

        for s in scale:
            if s not in ENV_SCALES:
                raise typer.BadParameter(f"--scale {s!r}: choose from {', '.join(ENV_SCALES)}")
        for name in env:
            if name not in PRESETS:
                raise typer.BadParameter(f"--env {name!r}: choose from {', '.join(PRESETS)}")
        _check_arch(arch)
        run_environment_bench(scale, env, _echo_json, progress=not no_progress, arch=arch)

    @bench.command("accuracy")
    def bench_accuracy(
        problem: list[str] = typer.Option([], "--problem", help="Reference problem(s) (default: all): bar, "
                                          "water_column, granular_column, robot_ground, robot_desert, gradient."),
        quick: bool = typer.Option(False, "--quick", help="Tiny sizes (seconds per problem) instead of the default."),
        report: Optional[Path] = typer.Option(None, "--report", help="Also write DIR/accuracy.md with one Pareto "
                                              "plot per problem (DIR/images/) and DIR/data/accuracy-SIZE.jsonl."),
        from_file: Optional[Path] = typer.Option(None, "--from", help="Write the report from these JSON lines "
                                                 "instead of measuring."),
        no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bar."),
    ) -> None:
        """Error against wall time and peak memory of reference problems with known or converged answers,
        over dx, particles per cell, cfl, float32/float64 and the checkpoint interval."""
        from codesign_mpm.reports.accuracy import PROBLEMS, run_accuracy_bench
        from codesign_mpm.reports.documents import write_accuracy_report

        for name in problem:
            if name not in PROBLEMS:
                raise typer.BadParameter(f"--problem {name!r}: choose from {', '.join(PROBLEMS)}")

        size = "quick" if quick else "default"
        _measure_or_read(lambda: run_accuracy_bench(problem or list(PROBLEMS), size, _echo_json,
                                                    progress=not no_progress),
                         from_file, report, write_accuracy_report)

    @bench.command("stability")
    def bench_stability(
        case: list[str] = typer.Option([], "--case", help="Hard case(s) (default: all; see docs/stability.md)."),
        quick: bool = typer.Option(False, "--quick", help="Short horizons and fewer settings (seconds per case)."),
        report: Optional[Path] = typer.Option(None, "--report", help="Also write DIR/stability.md and "
                                              "DIR/data/stability-SIZE.jsonl."),
        from_file: Optional[Path] = typer.Option(None, "--from", help="Write the report from these JSON lines."),
        no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bar."),
    ) -> None:
        """Hard cases run forward and backward at several settings: max |v|, min/max J, energy drift,
        gradient norms, and any non-finite value or error raised."""
        from codesign_mpm.reports.documents import write_stability_report
        from codesign_mpm.reports.stability import CASES, run_stability_bench

        for name in case:
            if name not in CASES:
                raise typer.BadParameter(f"--case {name!r}: choose from {', '.join(CASES)}")

        size = "quick" if quick else "default"
        _measure_or_read(lambda: run_stability_bench(case or list(CASES), size, _echo_json, progress=not no_progress),
                         from_file, report, write_stability_report)

    @bench.command("compile")
    def bench_compile(
        cover: list[str] = typer.Option([], "--cover", help="Ground cover under the robot (none, sand, snow, "
                                        "clay, mud, water); repeatable; default: all."),
        dtype: str = typer.Option("float32", "--dtype", help="float32 or float64."),
        no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bar."),
    ) -> None:
        """Seconds to compile a new scene's forward and backward kernels with an empty offline cache:
        a muscle-actuated robot on each ground cover, each in its own process."""
        from codesign_mpm.reports.bench import COVERS, run_compile_bench

        for c in cover:
            if c not in COVERS:
                raise typer.BadParameter(f"--cover {c!r}: choose from {', '.join(COVERS)}")
        if dtype not in ("float32", "float64"):
            raise typer.BadParameter(f"--dtype {dtype!r}: choose from float32, float64")
        run_compile_bench(list(cover or COVERS), dtype, _echo_json, progress=not no_progress)

    @bench.command("engine")
    def bench_engine(
        scale: list[str] = typer.Option(["small"], "--scale", help="tiny (1,024 particles, dx 1/32), small "
                                        "(7,200, dx 1/64), paper (61,504, dx 1/128) and/or large "
                                        "(476,288, dx 1/128); repeatable."),
        measure: list[str] = typer.Option([], "--measure", help="forward, float64, dense, backward, batch, "
                                          "scatter, adaptive, flip, contact; repeatable; default: all."),
        frames: int = typer.Option(200, "--frames", min=1, help="Frames of the differentiable episode."),
        segment_memory: list[int] = typer.Option([], "--segment-memory", min=0, help="MB a differentiable "
                                                 "episode may keep its states in (CODESIGN_SEGMENT_MEMORY_MB; "
                                                 "0: the memory-optimal segment); repeatable: the backward "
                                                 "measurement at each, memory against time [default: 256]."),
        members: Optional[int] = typer.Option(None, "--members", min=2, help="Episodes in the batch "
                                              "measurement [default: 8]; with --profile, a batched simulator "
                                              "of that many is profiled too."),
        profile: bool = typer.Option(False, "--profile", help="Instead: where a substep's time goes (kernel "
                                     "launches, Python-side field accesses, each kernel's share, the rest), "
                                     "forward and forward + backward, under Taichi's kernel profiler."),
        arch: str = typer.Option("cpu", "--arch", help="cpu or cuda."),
        no_progress: bool = typer.Option(False, "--no-progress", help="Hide the progress bar."),
    ) -> None:
        """Forward particle-substeps/s (float32, float64, dense grid), (forward + backward) / forward
        with checkpointing, peak memory of a differentiable episode, first-call (compile) time, and
        8 episodes in one batched simulator against the same 8 one after the other, and p2g's
        private-grid scatter against atomic adds; or (--profile) where a substep's time goes."""
        from codesign_mpm.reports.bench import ENGINE_MEASURES, SCALES, run_engine_bench, run_profile_bench

        for s in scale:
            if s not in SCALES:
                raise typer.BadParameter(f"--scale {s!r}: choose from {', '.join(SCALES)}")
        for m in measure:
            if m not in ENGINE_MEASURES:
                raise typer.BadParameter(f"--measure {m!r}: choose from {', '.join(ENGINE_MEASURES)}")
        if segment_memory and (profile or (measure and "backward" not in measure)):
            raise typer.BadParameter("--segment-memory sizes the backward measurement: add --measure backward "
                                     "(and no --profile)")
        _check_arch(arch)
        if profile:
            run_profile_bench(scale, arch, _echo_json, progress=not no_progress, members=members or 0)
        else:
            run_engine_bench(scale, frames, _echo_json, progress=not no_progress, arch=arch,
                             measures=tuple(measure or ENGINE_MEASURES), members=members or 8,
                             segment_memory_mb=tuple(segment_memory))
