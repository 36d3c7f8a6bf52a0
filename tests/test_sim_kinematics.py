"""UR5e closed-form IK: every solution reaches the pose, and the configuration the arm is in is found."""

from __future__ import annotations

import math

import numpy as np

from sim_cell import kinematics


def test_inverse_round_trips_random_configurations():
    rng = np.random.default_rng(3)
    for _ in range(300):
        q = rng.uniform(-math.pi, math.pi, 6)
        q[4] = math.copysign(max(abs(q[4]), 0.05), q[4])          # away from the wrist singularity
        target = kinematics.forward(q)
        solutions = kinematics.inverse(target)
        assert 1 <= len(solutions) <= 8
        for s in solutions:
            dp, dr = kinematics.pose_error(s, target)
            assert dp < 1e-9 and dr < 1e-6
        # the configuration the pose came from is one of the solutions
        wrapped = np.remainder(q + math.pi, 2 * math.pi) - math.pi
        assert min(np.max(np.abs(s - wrapped)) for s in solutions) < 1e-7
        near = kinematics.nearest_solution(solutions, q + rng.normal(0.0, 1e-6, 6))
        assert np.max(np.abs(near - q)) < 1e-7


def test_out_of_reach_pose_has_no_solution_and_nearest_of_none_is_none():
    far = np.eye(4)
    far[:3, 3] = (1.5, 0.0, 0.2)
    assert kinematics.inverse(far) == []
    assert kinematics.nearest_solution([], np.zeros(6)) is None


def test_nearest_solution_shifts_a_joint_by_two_pi_when_nearer_within_limits():
    q_ref = np.array([3.0, -1.0, 1.0, -1.5, -1.5, 3.1])
    sol = np.array([-3.0, -1.0, 1.0, -1.5, -1.5, -3.1])     # the same pose, joints 1 and 6 wrapped
    out = kinematics.nearest_solution([sol], q_ref)
    assert np.allclose(out, [-3.0 + 2 * math.pi, -1.0, 1.0, -1.5, -1.5, -3.1 + 2 * math.pi])


def test_inverse_many_gives_inverse_s_solutions_in_its_order_and_nothing_out_of_reach():
    from sim_cell.kinematics import forward_many, inverse_many

    rng = np.random.default_rng(3)
    qs = rng.uniform(-np.pi, np.pi, (200, 6))
    poses = forward_many(qs)
    far = np.eye(4)
    far[:3, 3] = (2.0, 0.0, 0.5)   # out of the UR5e's reach
    poses = np.concatenate([poses, far[None]])
    batch = inverse_many(poses)
    for i, pose in enumerate(poses):
        if i < len(qs):
            assert np.allclose(pose, kinematics.forward(qs[i]))
        solutions = kinematics.inverse(pose)
        valid = [q for q in batch[i] if not np.isnan(q[0])]
        assert len(valid) == len(solutions)
        assert all(np.allclose(a, b, atol=1e-9) for a, b in zip(valid, solutions))
    assert np.isnan(batch[-1]).all()
