"""Registers this package's representations and the `annotate` command; imports nothing heavy."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Optional

from codesign.hookspecs import hookimpl
from codesign.registry import PluginRegistrar

if TYPE_CHECKING:
    import typer


def _indices(option: str, text: str) -> list[int]:
    """'1,2' -> [1, 2]; anything else is an error naming the option."""
    from codesign_designs.annotate import AnnotationError

    try:
        return [int(part) for part in text.split(",")]
    except ValueError:
        raise AnnotationError(f"{option} {text}: expected comma-separated group numbers, e.g. 1,2") from None


@hookimpl
def codesign_register(registry: PluginRegistrar) -> None:
    registry.add(
        "representation",
        "particle",
        "codesign_designs.particle:ParticleRepresentation",
        "codesign_designs.config:ParticleConfig",
        "Per-particle logits (SoftZoo PBR): sigmoid occupancy and stiffness, softmax muscle membership.",
    )
    for name, module, cls, description in (
        ("fixed", "fixed", "Fixed", "The environment's body as it is (Table 1's animals): its stiffness, muscles and "
                                    "fibres, passive material passive; nothing to optimise."),
        ("voxel", "voxel", "Voxel", "Per-voxel logits on a grid of its own (SoftZoo VBR), trilinear or nearest."),
        ("implicit", "implicit", "Implicit", "An MLP on particle coordinates, plane distances and radius."),
        ("diff_cppn", "diff_cppn", "DiffCPPN", "A fixed-topology CPPN of mixed activations with gated edges."),
        ("sdf_lerp", "sdf_lerp", "SdfLerp", "Weighted SDFs of design primitives (fish family, animals); "
                                            "lerped stiffness and muscles, Procrustes-averaged fibres."),
        ("wasserstein", "wasserstein", "Wasserstein", "Debiased Sinkhorn barycenter of design primitives' "
                                                      "occupancy; the rest as sdf_lerp."),
        ("neat_cppn", "neat_cppn", "NeatCPPN", "A NEAT genome's CPPN (neat-python), evolved by the cppn_neat "
                                               "optimizer; the largest connected body is kept."),
    ):
        registry.add("representation", name, f"codesign_designs.{module}:{cls}Representation",
                     f"codesign_designs.config:{cls}Config", description)


@hookimpl
def codesign_cli(app: typer.Typer) -> None:
    import typer  # already loaded by the CLI

    @app.command()
    def annotate(
        body_file: str = typer.Argument(..., metavar="BODY_FILE", help="Mesh, point cloud, voxels, annotated .npz, "
                                                                       "or a library body name."),
        groups: int = typer.Option(..., "--groups", min=1, help="K: k-means groups before merging."),
        merge: list[str] = typer.Option([], "--merge", help="Groups to make one muscle, e.g. 1,2 (repeatable)."),
        passive: list[str] = typer.Option([], "--passive", help="Groups without muscle, e.g. 3 or 3,4 (repeatable)."),
        out: Optional[Path] = typer.Option(None, "--out", help="Annotated body file "
                                                               "[BODY_FILE stem + .annotated.npz]."),
        png: Optional[Path] = typer.Option(None, "--png", help="Also draw the groups to this PNG."),
        resolution: int = typer.Option(48, "--resolution", min=4, help="Samples along the longest side."),
        seed: int = typer.Option(0, "--seed", help="k-means seed."),
        symmetric: bool = typer.Option(False, "--symmetric", help="Cluster the body folded across its sagittal "
                                                                  "plane (z) and split every muscle into a left "
                                                                  "and a right one (paired limbs)."),
    ) -> None:
        """Label a body's muscles: k-means groups of its solid, each group's PCA axis as its fibre.

        Groups are numbered by their centre along x (tail to head); run once, look at --png,
        then run again with --merge and --passive.
        """
        import numpy as np

        from codesign.bodies import get_body
        from codesign_designs.annotate import annotate as label, render_annotation, save_annotation

        result = label(get_body(body_file), groups, [_indices("--merge", m) for m in merge],
                       [g for p in passive for g in _indices("--passive", p)], resolution, seed, symmetric)
        target = out or Path(Path(body_file).stem + ".annotated.npz")
        save_annotation(result, target)
        for muscle, (name, axis) in enumerate(zip(result.group_names, result.axes)):
            count = int((result.groups == muscle).sum())
            typer.echo(f"muscle {muscle}: {name}, {count} samples, fibre {np.round(axis, 3).tolist()}")
        typer.echo(f"passive: {int((result.groups < 0).sum())} samples")
        typer.echo(f"wrote {target}")
        if png is not None:
            render_annotation(result, png, title=f"{Path(body_file).name}: {len(result.group_names)} muscles")
            typer.echo(f"wrote {png}")
