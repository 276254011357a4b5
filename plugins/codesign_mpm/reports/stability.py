"""Which hard cases stay stable: `codesign bench stability`.

Each case of `CASES` builds a scene, runs it forward for its horizon (recording max |v|, min and
max J = det F and the mechanical energy), then a short differentiable rollout (from the state
the forward run reached) and its backward pass (recording gradient norms), at several settings,
each in its own process. Outcomes:

- `finite`: every state and gradient stayed finite;
- `clear error`: the engine refused or stopped with an error naming what went wrong
  (`SimulationError`, `SceneError`, a `CodesignError`) while the state was still finite: a pass
  only for a case whose input is outside the admissible range (`Case.admissible` False), a failure
  for an admissible one, which must run its whole horizon;
- `NON-FINITE`: a NaN or infinity appeared (in the state, the energy or a gradient): a failure;
- `crash`: any other exception: a failure.

The forward run also audits energy: the mechanical energy gained beyond the muscles' work
(`Simulator.audit_work`), which friction, contact, plasticity and APIC's transfers can only keep
negative; a positive excess is energy the integrator created.

The robot cases share one simulator layout (the robot of tests/mpm/test_engine_f64.py: dx 1/32,
12 differentiable frames, checkpoints every 64 substeps) and the material cases the layouts of
tests/mpm/gradient_checks.py, so their backward kernels compile once per machine.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Callable

import numpy as np

from codesign_mpm.reports.accuracy import GRAD_MAX_FRAMES, GRAD_SEGMENT, Setting, gradient_scene

GRAVITY = 3.8


@dataclass(frozen=True)
class Size:
    settings: list[Setting]
    frames_forward: int
    frames_backward: int


@dataclass(frozen=True)
class Case:
    name: str
    description: str
    build: Callable  # (setting) -> (sim, initial state (set_initial_state keywords) or None, actions(frame) -> (K,))
    sizes: dict[str, Size] = field(default_factory=dict)
    backward_from_end: bool = True  # the differentiable rollout starts where the forward run ended
    admissible: bool = True  # inside the documented input range: must run its whole horizon finite


def passed(record: dict) -> bool:
    """finite, or a clear error for an input outside the admissible range."""
    return record["outcome"] == "finite" or (record["outcome"] == "clear error" and not record.get("admissible", True))


ROBOT_SETTINGS = [Setting(dtype="float64"), Setting(dtype="float64", cfl=0.8), Setting(dtype="float32")]
MATERIAL_SETTINGS = [Setting(dtype="float64"), Setting(dtype="float64", cfl=0.8)]


def _robot_sizes(settings=ROBOT_SETTINGS) -> dict[str, Size]:
    return {"quick": Size([Setting(dtype="float64")], 10, 3), "default": Size(settings, 250, GRAD_MAX_FRAMES)}


def bang_bang(k: int, amplitude: float = 0.3) -> Callable[[int], np.ndarray]:
    """Full actuation, switching sign every 4 frames, neighbouring muscles in antiphase."""
    signs = np.where(np.arange(k) % 2 == 0, 1.0, -1.0)
    return lambda f: amplitude * (1.0 if f % 8 < 4 else -1.0) * signs


def _robot(s: Setting, **changes):
    """The shared robot simulator, its particles changed as the case says."""
    from codesign_mpm import build_particles
    from codesign_mpm.environment.config import FLIP_DEFAULT
    from codesign_mpm.engine import Simulator

    scene = replace(gradient_scene(s), flip=FLIP_DEFAULT)  # the FLIP share a recipe's robot runs with
    sim = Simulator(scene, build_particles(scene), requires_grad=True, max_frames=GRAD_MAX_FRAMES,
                    checkpoint_every=GRAD_SEGMENT)  # allocated first: the layout of tests/mpm/test_engine_f64.py
    body = scene.bodies[0]
    for key, value in changes.items():
        if key in ("youngs_modulus",):
            setattr(body.material, key, value)
        else:
            setattr(body, key, value)
    if changes:
        sim.reset(build_particles(scene))
    return sim


def stiff_body(s: Setting):
    sim = _robot(s, youngs_modulus=1e6)  # 100x the default: the CFL step shrinks about 10x
    return sim, None, bang_bang(sim.n_actuators)


def fast_impact(s: Setting):
    sim = _robot(s, rest_on_terrain=False, center=[0.5, 0.25, 0.25], velocity=[0.0, -8.0, 0.0])
    return sim, None, lambda f: np.zeros(sim.n_actuators)


def full_actuation(s: Setting):
    sim = _robot(s)
    return sim, None, bang_bang(sim.n_actuators)


def near_inverted(s: Setting):
    sim = _robot(s)
    F = np.tile(np.eye(3), (sim.n, 1, 1))
    F[::7] = np.diag([0.1, 0.1, 0.1])  # J = 1e-3
    F[3] = np.diag([-0.05, 1.0, 1.0])  # inverted
    return sim, {"F": F}, bang_bang(sim.n_actuators)


def tiny_mass(s: Setting):
    sim = _robot(s)
    volume = sim.particles.volume.copy()
    volume[::2] *= 1e-9
    sim.set_design(volume=volume)
    return sim, None, bang_bang(sim.n_actuators)


def leaving_domain(s: Setting):
    """Thrown at the +x wall (4 units/s) and upwards under full actuation: the walls must hold it
    (or the engine must say it left), never NaN."""
    sim = _robot(s, rest_on_terrain=False, center=[0.8, 0.3, 0.25], velocity=[4.0, 2.0, 0.0])
    return sim, None, bang_bang(sim.n_actuators)


def under_load(environment: str):
    """The robot fully actuated in an environment preset (dx 1/32): the cover carries its load."""
    def build(s: Setting):
        from codesign_mpm.environment.config import PRESET_CONFIGS, PRESETS, TerrainConfig
        from codesign_mpm.engine import Simulator
        from codesign_mpm.environment.env import LocomotionEnv

        preset = PRESETS[environment]
        config = PRESET_CONFIGS[environment](dx=1 / 32, horizon=50, dtype=s.dtype, cfl=s.cfl, terrain=TerrainConfig(
            height=0.1, friction=preset.friction))  # as tests/mpm/test_environments.py's make_env
        env = LocomotionEnv(config, preset)
        sim = Simulator(env.scene, env.particles, requires_grad=True, max_frames=GRAD_MAX_FRAMES,
                        checkpoint_every=GRAD_SEGMENT)
        return sim, env.initial_state(env.particles), bang_bang(sim.n_actuators)
    return build


CASES: dict[str, Case] = {
    "stiff_body": Case("stiff_body", "A robot 100x stiffer than the default (E 1e6), fully actuated "
                       "(bang-bang 0.3): the CFL step shrinks about 10x.", stiff_body, _robot_sizes()),
    "fast_impact": Case("fast_impact", "The robot dropped onto frictional ground at 8 units/s (the step "
                        "adapts to the initial speed).", fast_impact, _robot_sizes()),
    "full_actuation": Case("full_actuation", "Maximum actuation (bang-bang at the bound 0.3, switching every "
                           "4 frames) over a long horizon; the backward pass starts from the end state.",
                           full_actuation, _robot_sizes()),
    "near_inverted": Case("near_inverted", "One particle in seven crushed to J = 1e-3 and one inverted "
                          "(J = -0.05) at the start, then full actuation.", near_inverted, _robot_sizes()),
    "tiny_mass": Case("tiny_mass", "Every other particle at 1e-9 of its mass, full actuation (designs keep "
                      "particles of at least half their sampled mass).", tiny_mass, _robot_sizes(), admissible=False),
    "leaving_domain": Case("leaving_domain", "The robot thrown at the +x wall at 4 units/s (and up at 2) "
                           "under full actuation: free-slip walls must hold it.", leaving_domain, _robot_sizes()),
}
for _env in ("desert", "snow", "clay", "wetland", "shallow_water", "ocean"):
    CASES[f"load_{_env}"] = Case(
        f"load_{_env}", f"The robot fully actuated in the `{_env}` environment (dx 1/32, settled cover): "
        "the cover material under a robot's load.", under_load(_env),
        {"quick": Size([Setting(dtype="float64")], 10, 3), "default": Size(MATERIAL_SETTINGS, 150, GRAD_MAX_FRAMES)})


# ------------------------------------------------------------------------------------- measuring
def energy(sim, x, v, F) -> tuple[float, float]:
    """(kinetic + gravitational + neo-Hookean elastic energy, kinetic energy); the elastic energy is the
    one the engine integrates (its volumetric part continued below J_MIN, `volumetric_energy`)."""
    from codesign_mpm.materials import ID, lame
    from codesign_mpm.materials.neo_hookean import volumetric_energy

    p = sim.particles
    m = p.volume * p.density
    x, v, F = (np.asarray(a, dtype=np.float64) for a in (x, v, F))
    kinetic = 0.5 * float(m @ (v * v).sum(1))
    total = kinetic + GRAVITY * float(m @ x[:, 1])
    elastic = p.material == ID["neo_hookean"]
    J = np.linalg.det(F)
    ok = elastic & (J > 0)
    if ok.any():
        mu, la = lame(p.youngs_modulus[ok], p.poisson_ratio[ok])
        logJ = np.log(J[ok])
        psi = 0.5 * mu * ((F[ok] ** 2).sum((1, 2)) - 3) - mu * logJ + la * volumetric_energy(J[ok])
        total += float(p.volume[ok] @ psi)
    return total, kinetic


def _finite(*arrays) -> bool:
    return all(np.isfinite(np.asarray(a, dtype=np.float64)).all() for a in arrays if a is not None)


def run_case(name: str, size: str, s: Setting) -> dict:
    """One case at one setting, in this process."""
    from codesign.errors import CodesignError
    from codesign_mpm import runtime
    from codesign_mpm.engine import SimulationError, State
    from codesign_mpm.scene.spec import SceneError

    runtime.reset()
    runtime.init_taichi("cpu", s.dtype)
    case, spec = CASES[name], CASES[name].sizes[size]
    record = dict(frames_forward=spec.frames_forward, frames_backward=spec.frames_backward, admissible=case.admissible)
    sim, stage = None, "building"
    t0 = time.perf_counter()
    try:
        sim, initial, actions = case.build(s)
        record.update(particles=sim.n, substeps_per_frame=sim.timestep.substeps, dt=sim.timestep.dt)
        if initial is not None:
            sim.set_initial_state(**initial)
        x, v, _, F = sim.particles_state()
        e0, _ = energy(sim, x, v, F)
        sim.audit_work = True
        kmax = 0.0
        scale = GRAVITY * float(sim.particles.volume @ sim.particles.density) * sim.scene.size[1]
        stage = "forward"
        for f in range(spec.frames_forward):
            sim.step(actions(f))
            x, v, _, F = sim.particles_state()
            if not _finite(x, v, F):
                record.update(outcome="NON-FINITE", message=f"non-finite state after frame {f + 1}")
                return record
            # statistics so far: a run that stops with an error keeps what it reached
            J = np.linalg.det(F.astype(np.float64))
            e1, kinetic = energy(sim, x, v, F)
            kmax = max(kmax, kinetic)
            record.update(frames_reached=f + 1, max_speed=max(record.get("max_speed", 0.0), float(np.abs(v).max())),
                          min_J=min(record.get("min_J", np.inf), float(J.min())),
                          max_J=max(record.get("max_J", -np.inf), float(J.max())),
                          energy_drift=(e1 - e0) / max(abs(e0), kmax, scale),
                          energy_excess=max(record.get("energy_excess", -np.inf),
                                            (e1 - e0 - sim.muscle_work) / max(abs(e0), kmax, scale)),
                          substeps_mean=float(np.mean(sim.frame_substeps)),
                          substeps_max=int(max(sim.frame_substeps)))
        stage = "backward"
        start = State(*(np.asarray(a, dtype=np.float64) for a in (*sim.particles_state(), sim.plastic_volume_ratio())))
        T = spec.frames_backward
        out = sim.rollout(np.stack([actions(spec.frames_forward + f) for f in range(T)]),
                          start=start if case.backward_from_end else None)
        seed = np.zeros_like(out.com_x)
        seed[-1, 0], seed[0, 0] = 1.0, -1.0  # loss: distance travelled along x
        g = sim.backward(com_x=seed)
        E = sim.particles.youngs_modulus
        record.update(grad_actions_norm=float(np.linalg.norm(g.actions)),
                      grad_stiffness_norm=float(np.linalg.norm(g.youngs_modulus * E)),
                      grad_x0_norm=float(np.linalg.norm(g.x0)))
        finite = _finite(out.com_x, out.x, g.actions, g.youngs_modulus, g.x0, g.v0, g.F0) and np.isfinite(e1)
        record["outcome"] = "finite" if finite else "NON-FINITE"
        if not finite:
            record["message"] = "non-finite gradient or state in the differentiable rollout"
    except (SimulationError, SceneError, CodesignError, ValueError) as exc:
        state_finite = True
        if sim is not None:
            try:
                state_finite = _finite(*sim.particles_state())
            except Exception:  # noqa: BLE001 - the state could not be read: say so through the outcome
                state_finite = False
        record.update(outcome="clear error" if state_finite else "NON-FINITE",
                      message=f"{stage}: {type(exc).__name__}: {str(exc).splitlines()[0]}")
    except Exception as exc:  # noqa: BLE001 - anything else is a failure, recorded with its message
        record.update(outcome="crash", message=f"{stage}: {type(exc).__name__}: {str(exc).splitlines()[0]}")
    finally:
        record["wall_s"] = time.perf_counter() - t0
        if sim is not None:
            sim.close()
    return record


def _isolated(name: str, size: str, s: Setting) -> dict:
    from codesign_mpm.reports.machine import run_module

    record, error = run_module("codesign_mpm.reports.stability", name, size, json.dumps(asdict(s)))
    return dict(outcome="crash", message=error) if error else record


def run_stability_bench(cases: list[str], size: str, emit, isolate: bool = True,
                        progress: bool = True) -> list[dict]:
    """Emit one JSON object per (case, setting); returns them all."""
    from codesign.progress import progress_bar
    from codesign_mpm.reports.machine import machine_description

    machine = machine_description()
    rows = []
    runs = [(name, s) for name in cases for s in CASES[name].sizes[size].settings]
    for name, s in progress_bar(runs, desc="bench stability", unit="run", show=progress):
        t0 = time.perf_counter()
        record = _isolated(name, size, s) if isolate else run_case(name, size, s)
        row = dict(measure="stability", case=name, size=size, setting=s.label(), **asdict(s), **record,
                   process_s=round(time.perf_counter() - t0, 2), machine=machine)
        emit(row)
        rows.append(row)
    return rows


if __name__ == "__main__":  # one isolated run: CASE SIZE SETTING_JSON
    print(json.dumps(run_case(sys.argv[1], sys.argv[2], Setting(**json.loads(sys.argv[3])))))
