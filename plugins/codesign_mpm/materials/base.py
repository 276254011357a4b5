"""What a material model is to the engine: `MaterialModel`, its `Parameter`s, and `ti`.

A material model is one module (see the built-in ones next to this file, and docs/plugins.md for
a plugin's): it defines `MODEL`, a `MaterialModel` that names the model, its per-particle
parameters (defaults, valid ranges), its fastest wave speed for the time step, and its Taichi
functions: the Kirchhoff stress of an elastic model, the principal-strain return mapping of a
plastic (Hencky) model, or the update of a fluid. The engine compiles those functions into its
kernels (as `ti.func`) only for the models a scene uses, dispatching on the model's id with
`ti.static`, so a model costs nothing where it is absent.

Material modules stay light: they use `ti` from here, a stand-in that imports Taichi only when
a kernel is compiled, so that scenes can be validated, and `codesign plugins` list the models,
without importing Taichi.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

KINDS = ("elastic", "hencky", "fluid")
"""elastic: the stress is a function of F alone (F evolves as (I + dt C) F);
hencky: elastoplastic in principal Hencky strain (a return mapping of b = F F^T's eigenvalues);
fluid: the model updates F itself (water keeps only J)."""


class _Taichi:
    """`taichi`, imported on first use (material modules are imported by light code too)."""

    def __getattr__(self, name: str) -> Any:
        import taichi

        return getattr(taichi, name)


ti: Any = _Taichi()


def func(function: Callable) -> Callable:
    """Marks a material module's Taichi function: compiled with `ti.func` the first time a kernel
    calls it (so the module imports no Taichi), then inlined into that kernel like any `ti.func`.
    The result is a plain function, so kernels may pass it through `ti.static`."""
    compiled: list[Callable] = []

    @functools.wraps(function)
    def call(*args):
        if not compiled:
            import taichi

            compiled.append(taichi.func(function))
            call.func = compiled[0].func  # what Taichi reads of a `ti.func` it called (has_print)
        return compiled[0](*args)

    call._is_taichi_function = True  # type: ignore[attr-defined]  # Taichi: a function of its own, not Python's
    return call


@func
def cofactor(F):
    """d det(F) / dF, the cofactor matrix (defined for singular F too)."""
    cof = ti.Matrix.zero(float, 3, 3)
    for i, j in ti.static(ti.ndrange(3, 3)):
        cof[i, j] = (F[(i + 1) % 3, (j + 1) % 3] * F[(i + 2) % 3, (j + 2) % 3]
                     - F[(i + 1) % 3, (j + 2) % 3] * F[(i + 2) % 3, (j + 1) % 3])
    return cof


def lame(youngs_modulus: float, poisson_ratio: float) -> tuple[float, float]:
    """(mu, lambda) from Young's modulus and Poisson's ratio."""
    mu = youngs_modulus / (2 * (1 + poisson_ratio))
    lam = youngs_modulus * poisson_ratio / ((1 + poisson_ratio) * (1 - 2 * poisson_ratio))
    return mu, lam


def elastic_wave_speed(youngs_modulus: float, poisson_ratio: float, density: float,
                       added_modulus: float = 0.0) -> float:
    """Fastest elastic (P-)wave speed, sqrt((lambda + 2 mu + added) / rho); muscles add to the modulus."""
    mu, lam = lame(youngs_modulus, poisson_ratio)
    return math.sqrt((lam + 2 * mu + added_modulus) / density)


def _elastic_speed(youngs_modulus: float, poisson_ratio: float, density: float, added_modulus: float,
                   params: tuple[float, ...]) -> float:
    return elastic_wave_speed(youngs_modulus, poisson_ratio, density, added_modulus)


@dataclass(frozen=True)
class Parameter:
    """One per-particle number a model reads, as a scene's material gives it.

    `name` is a field of `codesign_mpm.scene.spec.MaterialSpec` (the built-in models' parameters) or a
    key of its `parameters` mapping (a plugin model's own)."""

    name: str
    default: float
    check: Callable[[float], bool]
    allowed: str  # what a SceneError says is allowed
    help: str = ""


@dataclass(frozen=True)
class MaterialModel:
    """One constitutive model (see the module docstring). Functions marked Taichi are compiled into
    the engine's kernels; `mu`, `la` are the particle's Lame parameters, `prm` its parameter vector
    (N_PARAMS numbers: `pack`'s output, zero-padded)."""

    name: str
    description: str
    kind: str = "elastic"
    parameters: tuple[Parameter, ...] = ()
    pack: Callable[[dict[str, float]], tuple[float, ...]] | None = None
    """The parameter vector from the parameters' values (default: the values in order)."""
    wave_speed: Callable[..., float] = _elastic_speed
    """(E, nu, rho, added axial modulus of a muscle, params) -> fastest wave speed at rest (CFL)."""
    viscosity_index: int | None = None
    """Where the dynamic viscosity eta sits in the parameter vector: the engine adds the Newtonian
    stress J eta (C + C^T) (APIC's C as the velocity gradient) and the explicit diffusion limit."""
    stress: Callable | None = None
    """elastic (Taichi): (F, mu, la) -> Kirchhoff stress tau = P F^T; (F, mu, la, prm) for a model
    with `parameters`."""
    stress_adjoint: Callable | None = None
    """elastic, optional (Taichi): (F, mu, la, nu, tau_bar, E_bar) -> (F_bar, E_bar): the stress's
    adjoint written by hand (E_bar: Young's modulus's gradient so far, returned with this stress's
    added). Without it, Taichi's reverse mode differentiates `stress`."""
    return_map: Callable | None = None
    """hencky (Taichi): (eps, tr, dev, n2, prm, mu, la) -> (eps_new, alpha): the principal Hencky
    strain eps (trace tr, deviator dev with |dev|^2 = n2) projected onto the elastic region, and
    the slope alpha of that (per particle affine) map; written branch-free (see `clay`)."""
    plastic_volume: bool = False
    """hencky: the plastic volume ratio J_p is state (snow's hardening); such a model gives both:"""
    projection_slope: Callable | None = None
    """(Taichi): (eps, eps_new, scale, a) -> (inside, slope): the slope in a of the projection's scale
    exp(eps_new - eps) (and a mask `principal_stress` may use), where the return map is not affine."""
    principal_stress: Callable | None = None
    """(Taichi): (eps_new, inside, jp, prm, mu, la) -> (k, k_slope): a principal Kirchhoff stress other
    than Hencky's 2 mu eps_new + lambda tr(eps_new) (snow's), with J_p = jp updated by the map."""
    update: Callable | None = None
    """fluid (Taichi): (F, prm) -> (F to store, tau)."""
    differentiable: bool = True
    """False: refused in differentiable simulators (corotated: Taichi has no reverse mode of its polar decomposition)."""
    id: int = -1
    """Assigned when the model is registered (`codesign_mpm.materials.register`): the kernels' dispatch key."""

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"material '{self.name}': kind {self.kind!r} is not one of {', '.join(KINDS)}")
        needed = {"elastic": "stress", "hencky": "return_map", "fluid": "update"}[self.kind]
        if getattr(self, needed) is None:
            raise ValueError(f"material '{self.name}' of kind {self.kind} needs its `{needed}` function")

    @property
    def elastic_with_parameters(self) -> bool:
        """An elastic model whose stress reads a parameter vector (`stress(F, mu, la, prm)`)."""
        return self.kind == "elastic" and bool(self.parameters)

    @property
    def viscous(self) -> bool:
        """The engine adds a Newtonian stress (`viscosity_index`)."""
        return self.viscosity_index is not None

    @property
    def hand_adjoint(self) -> bool:
        """An elastic model whose whole stress has its adjoint written by hand (`stress_adjoint`;
        no parameter vector, no viscous term): the engine needs no reverse mode of Taichi's for it,
        and a differentiable scene of it alone runs it inside p2g's adjoint."""
        return self.stress_adjoint is not None and self.kind == "elastic" and not self.parameters and not self.viscous

    @property
    def plastic(self) -> bool:
        """True if the model changes F beyond (I + dt C) F (return mapping or fluid reset)."""
        return self.kind != "elastic"

    def packed(self, values: dict[str, float]) -> tuple[float, ...]:
        """The parameter vector (unpadded) from the parameters' values."""
        return self.pack(values) if self.pack else tuple(values[p.name] for p in self.parameters)

    def viscosity(self, params: tuple[float, ...]) -> float:
        """Dynamic viscosity of a particle with the parameter vector `params` (0 without a viscous term)."""
        return params[self.viscosity_index] if self.viscosity_index is not None else 0.0

    @property
    def config(self) -> type:
        """The parameters as a dataclass (what `codesign plugins` and the registry show)."""
        return dataclasses.make_dataclass(
            f"{self.name.title().replace('_', '')}Parameters",
            [(p.name, float, field(default=p.default, metadata={"help": p.help})) for p in self.parameters])
