"""The one path by which gradients cross from the simulator to torch parameters.

`simulate(sim, actions, volume=..., youngs_modulus=..., ...)` runs a differentiable rollout
and returns torch tensors (robot centre of mass per frame, final particle state); calling
`.backward()` on any loss built from them runs the simulator's checkpointed backward pass
and delivers gradients to every torch input that requires them.
"""
from __future__ import annotations

import numpy as np
import torch

from codesign_mpm.engine import Simulator, State

DESIGN_INPUTS = ("volume", "youngs_modulus", "muscle", "fiber")
STATE_INPUTS = ("x0", "v0")


def _run(sim: Simulator, checkpoint_every, actions: np.ndarray, design: dict, x0, v0):
    sim.set_design(**design)
    if x0 is not None or v0 is not None:
        sim.set_initial_state(x=x0, v=v0)
    return sim.rollout(actions, checkpoint_every=checkpoint_every)


def _replay_if_stale(ctx, start: State | None = None) -> None:
    """Make the simulator's last rollout this node's again (restore its design and initial state
    and recompute) if anything ran on the simulator since: backward() replays the last one."""
    sim = ctx.sim
    if sim.rollouts != ctx.rollout_id or not sim.rollout_is_current:
        sim.restore(ctx.snapshot)
        sim.rollout(ctx.actions, checkpoint_every=ctx.checkpoint_every, start=start)
        ctx.rollout_id = sim.rollouts


class _Rollout(torch.autograd.Function):
    @staticmethod
    def forward(ctx, sim: Simulator, checkpoint_every, actions, *inputs):
        host = [None if t is None else t.detach().cpu().numpy() for t in inputs]
        ctx.actions = actions.detach().cpu().numpy()
        ctx.sim, ctx.checkpoint_every = sim, checkpoint_every
        out = _run(sim, checkpoint_every, ctx.actions, dict(zip(DESIGN_INPUTS, host[:4])), *host[4:])
        # the whole design and initial state of this rollout, inputs left as None included, so a
        # recompute in backward replays exactly it whatever ran on the simulator in between
        ctx.snapshot = sim.snapshot()
        ctx.rollout_id = sim.rollouts
        ctx.present = [t is not None for t in inputs]
        ctx.dtype, ctx.device = actions.dtype, actions.device
        return tuple(torch.as_tensor(a, dtype=actions.dtype, device=actions.device)
                     for a in (out.com_x, out.com_v, out.x, out.v))

    @staticmethod
    def backward(ctx, g_com_x, g_com_v, g_x, g_v):
        def host(t):
            return None if t is None else t.detach().cpu().numpy().astype(np.float64)

        _replay_if_stale(ctx)
        grads = ctx.sim.backward(com_x=host(g_com_x), com_v=host(g_com_v), x=host(g_x), v=host(g_v))

        def dev(a):
            return torch.as_tensor(a, dtype=ctx.dtype, device=ctx.device)

        per_input = [grads.volume, grads.youngs_modulus, grads.muscle, grads.fiber, grads.x0, grads.v0]
        return (None, None, dev(grads.actions),
                *(dev(g) if present else None for g, present in zip(per_input, ctx.present)))


def simulate(sim: Simulator, actions: torch.Tensor, *, volume: torch.Tensor | None = None,
             youngs_modulus: torch.Tensor | None = None, muscle: torch.Tensor | None = None,
             fiber: torch.Tensor | None = None, x0: torch.Tensor | None = None, v0: torch.Tensor | None = None,
             checkpoint_every: int | None = None) -> tuple[torch.Tensor, ...]:
    """Differentiable rollout of len(actions) frames.

    Returns (com_x (T+1, 3), com_v (T+1, 3), x (N, 3), v (N, 3)) for the robot's centre of
    mass per frame and every particle at the end. Inputs left as None keep the simulator's
    current values and receive no gradient. If the simulator ran or changed anything else
    before backward (another rollout, `step`, `set_design`), this rollout's recorded design and
    initial state are restored and it is recomputed first (correct, at the cost of one forward).
    """
    return _Rollout.apply(sim, checkpoint_every, actions, volume, youngs_modulus, muscle, fiber, x0, v0)


STATE_FIELDS = ("x", "v", "C", "F", "Jp", "u")  # u: the spring contact's tangential springs (zeros elsewhere)


class _Frame(torch.autograd.Function):
    """One control step from a given state, for closed-loop episodes: the action may depend on
    the state, so each step is its own autograd node and gradients flow through observations.
    The design inputs must be the simulator's current design (`step_frame` sets it); autograd
    sums their gradients over the steps."""

    @staticmethod
    def forward(ctx, sim: Simulator, checkpoint_every, action, x, v, C, F, Jp, u, *design):
        ctx.sim, ctx.checkpoint_every = sim, checkpoint_every
        ctx.actions = action.detach().cpu().numpy()[None]
        ctx.start = State(*(t.detach().cpu().numpy() for t in (x, v, C, F, Jp, u)))
        ctx.snapshot = sim.snapshot()
        out = sim.rollout(ctx.actions, checkpoint_every=checkpoint_every, start=ctx.start)
        ctx.rollout_id = sim.rollouts
        ctx.dtype, ctx.device = x.dtype, x.device
        return tuple(torch.as_tensor(getattr(out.final, name), dtype=x.dtype, device=x.device)
                     for name in STATE_FIELDS)

    @staticmethod
    def backward(ctx, *grad_state):
        _replay_if_stale(ctx, ctx.start)  # later steps ran on the simulator
        seeds = {name: None if g is None else g.detach().cpu().numpy().astype(np.float64)
                 for name, g in zip(STATE_FIELDS, grad_state)}
        grads = ctx.sim.backward(**seeds)

        def dev(a):
            return torch.as_tensor(a, dtype=ctx.dtype, device=ctx.device)

        return (None, None, dev(grads.actions[0]),
                *(dev(g) for g in (grads.x0, grads.v0, grads.C0, grads.F0, grads.Jp0)),
                dev(grads.u0 if grads.u0 is not None else np.zeros_like(grads.x0)),
                *(dev(getattr(grads, name)) for name in DESIGN_INPUTS))


def step_frame(sim: Simulator, state: tuple[torch.Tensor, ...], action: torch.Tensor,
               design: tuple[torch.Tensor, ...], checkpoint_every: int | None = None) -> tuple[torch.Tensor, ...]:
    """Differentiable control step: state (x, v, C, F, Jp, u) -> the state one frame later, holding
    `action`, for the design (volume, youngs_modulus, muscle, fiber), applied to `sim` (a no-op
    when it is already its design)."""
    sim.set_design(**{name: t.detach().cpu().numpy() for name, t in zip(DESIGN_INPUTS, design)})
    return _Frame.apply(sim, checkpoint_every, action, *state, *design)
