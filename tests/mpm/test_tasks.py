"""Each task's reward on constructed motions with a known answer (no simulation)."""
import numpy as np
import pytest
import torch

from codesign_mpm.environment.tasks import MovementSpeed, RobotFrame, TaskContext, Turning, VelocityTracking, WaypointFollowing, quintic

DT, HORIZON = 8e-3, 50
REST = np.stack(np.meshgrid(np.linspace(-0.1, 0.1, 20), np.linspace(-0.04, 0.04, 5), np.linspace(-0.04, 0.04, 5),
                            indexing="ij"), -1).reshape(-1, 3) + [0.5, 0.1, 0.25]  # a box lattice: heading exactly +x
MASS = torch.as_tensor(np.random.default_rng(1).uniform(0.5, 2.0, len(REST)))


def frame(step: int, x: np.ndarray, v: np.ndarray, F: np.ndarray | None = None) -> RobotFrame:
    """The robot at step `step` with particles at x, moving at the constant velocities v since the step before."""
    x, v = torch.as_tensor(x), torch.as_tensor(v)
    w = MASS / MASS.sum()
    F = torch.eye(3, dtype=torch.float64).expand(len(x), 3, 3) if F is None else torch.as_tensor(F)
    return RobotFrame(step, step * DT, w @ x, w @ v, MASS, x, v, F, com_x_before=w @ (x - DT * v))


def started(task):
    com = (MASS.numpy() @ REST) / MASS.sum().item()
    task.start(TaskContext(rest_x=REST, start_com=com, control_dt=DT, horizon=HORIZON))
    return task, com


def test_movement_speed_of_a_rigid_translation_is_its_speed_along_the_direction():
    task, _ = started(MovementSpeed([2.0, 0.0, 0.0]))
    v = np.array([0.3, -0.1, 0.2])
    assert float(task.reward(frame(3, REST + 3 * DT * v, np.tile(v, (len(REST), 1))))) == pytest.approx(0.3)
    task, _ = started(MovementSpeed([1.0, 0.0, 1.0]))
    assert float(task.reward(frame(1, REST, np.tile(v, (len(REST), 1))))) == pytest.approx(0.5 / np.sqrt(2))


def test_movement_speed_is_the_distance_covered_over_the_step_not_the_velocity_at_its_end():
    """A body oscillating in phase with the control steps, at rest on average, sampled at its fast
    instants: com_v says 0.3 every step, the distance covered says 0."""
    task, com = started(MovementSpeed([1.0, 0.0, 0.0]))
    x, v = torch.as_tensor(REST), torch.as_tensor(np.tile([0.3, 0.0, 0.0], (len(REST), 1)))
    w = MASS / MASS.sum()
    still = RobotFrame(7, 7 * DT, w @ x, w @ v, MASS, x, v, None, com_x_before=w @ x)
    assert float(task.reward(still)) == 0.0
    with pytest.raises(ValueError, match="com_x_before"):
        task.reward(RobotFrame(7, 7 * DT, w @ x, w @ v))


@pytest.mark.parametrize("measure", ["tangent", "angular_momentum"])
@pytest.mark.parametrize("omega", [1.5, -0.7])
def test_turning_of_a_rigid_rotation_is_its_rate_times_the_mean_distance_from_the_axis(omega, measure):
    task, _ = started(Turning([0.0, 1.0, 0.0], measure))
    w = MASS.numpy() / MASS.sum().item()
    com = w @ REST
    # a translation on top does not turn it (the tangents' mean reads absolute velocities, as the paper's)
    drift = np.array([0.2, -0.1, 0.3]) if measure == "angular_momentum" else np.zeros(3)
    v = np.cross([0.0, omega, 0.0], REST - com) + drift
    radius = np.linalg.norm((REST - com)[:, [0, 2]], axis=1)
    assert float(task.reward(frame(1, REST, v))) == pytest.approx(omega * (w @ radius), rel=1e-9)


def test_bending_without_angular_momentum_scores_as_turning_by_tangents_only():
    """Material near the axis swinging counter-clockwise and material far from it clockwise, with no
    angular momentum in all: the tangents' mean (the paper's measure) is positive, the body's
    angular velocity zero."""
    w = MASS.numpy() / MASS.sum().item()
    r = REST - w @ REST
    radius2 = (r[:, [0, 2]] ** 2).sum(1)
    inner = radius2 < np.median(radius2)
    spin = np.where(inner, 1.0, -(w[inner] @ radius2[inner]) / (w[~inner] @ radius2[~inner]))  # rates: zero net momentum
    v = np.cross([0.0, 1.0, 0.0], r) * spin[:, None]
    tangent = float(started(Turning([0.0, 1.0, 0.0]))[0].reward(frame(1, REST, v)))
    momentum = float(started(Turning([0.0, 1.0, 0.0], "angular_momentum"))[0].reward(frame(1, REST, v)))
    assert tangent > 0.005 and abs(momentum) < 1e-12
    # both are smooth in the particles' positions and velocities (what diff-physics differentiates)
    for measure in ("tangent", "angular_momentum"):
        task = started(Turning([0.0, 1.0, 0.0], measure))[0]
        x0 = torch.as_tensor(REST[:12]).requires_grad_()
        v0 = torch.as_tensor(v[:12] + 0.1).requires_grad_()
        weights = MASS[:12]

        def reward(x, v):
            w = weights / weights.sum()
            return task.reward(RobotFrame(1, DT, w @ x, w @ v, weights, x, v))

        assert torch.autograd.gradcheck(reward, (x0, v0)), measure
    with pytest.raises(ValueError, match="turning measure 'yaw': choose from tangent, angular_momentum"):
        Turning([0.0, 1.0, 0.0], "yaw")


def test_quintic_meets_its_boundary_conditions():
    c = quintic([0, 0, 0], [1, 2, 3], [0.1, 0, 0], [0, 0.2, 0], [0, 0, 0.3], [0.4, 0, 0], duration=2.0)
    t = 2.0
    position = sum(c[k] * t ** k for k in range(6))
    velocity = sum(k * c[k] * t ** (k - 1) for k in range(1, 6))
    acceleration = sum(k * (k - 1) * c[k] * t ** (k - 2) for k in range(2, 6))
    np.testing.assert_allclose(position, [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(velocity, [0, 0.2, 0], atol=1e-12)
    np.testing.assert_allclose(acceleration, [0.4, 0, 0], atol=1e-12)
    np.testing.assert_allclose(c[1], [0.1, 0, 0]) and np.testing.assert_allclose(2 * c[2], [0, 0, 0.3])


def test_a_body_on_the_path_scores_zero_waypoint_error_and_its_off_set_squared_off_it():
    task, com = started(WaypointFollowing([0.3, 0.0, 0.1], [0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]))
    for step in (1, 17, HORIZON):
        shift = task.position(step * DT) - com
        assert float(task.reward(frame(step, REST + shift, np.zeros_like(REST)))) == pytest.approx(0, abs=1e-20)
        off = np.array([0.0, 0.02, 0.0])
        assert float(task.reward(frame(step, REST + shift + off, np.zeros_like(REST)))) == pytest.approx(-4e-4)
    np.testing.assert_allclose(task.info(HORIZON - 1), com + [0.3, 0.0, 0.1], atol=1e-12)  # the last waypoint is the end


def test_velocity_tracking_rewards_following_the_path_velocity_along_the_heading():
    task, com = started(VelocityTracking([0.4, 0.0, 0.0], [0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]))
    step = 20
    target = task.velocity(step * DT)
    v = np.tile(target, (len(REST), 1))
    # on the path, heading along it: the magnitude term vanishes and the direction term is |v*|
    assert float(task.reward(frame(step, REST, v))) == pytest.approx(0.9 * np.linalg.norm(target), rel=1e-9)
    # backwards at the same speed: the direction term flips sign
    assert float(task.reward(frame(step, REST, -v))) == pytest.approx(-0.9 * np.linalg.norm(target), rel=1e-9)
    # turned 90 degrees about y (the deformation gradients say so): the heading is -z, and a velocity
    # along the path (+x) has no component on it, so only -0.1 |v*|^2 remains
    R = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    turned = frame(step, REST, v, np.tile(R, (len(REST), 1, 1)))
    assert float(task.reward(turned)) == pytest.approx(-0.1 * np.linalg.norm(target) ** 2, abs=1e-5)  # |v_h| = eps
