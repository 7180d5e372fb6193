"""A path for the head around the plant to a pose, planned with OMPL.

A pollination visit comes down from the top of Z to its pre-approach pose. Where the straight
descent is blocked (a leaf over the flower), the head is routed round the foliage: a path in
the bot's five joints, gantry x, y, z and the head's yaw and pitch, searched by OMPL's
RRT-Connect and shortened by its path simplifier, every state of it clear by the caller's
test (`clear`: the head's housings and the pollinator keep their distance from the plant).

The joints are the servos' own angles (the solution the head takes, `kinematics.
joint_positions`), so a straight segment between two states is what the servos do, with no
jump where the yaw would flip. Angles count in path length as ANGLE_LEVER_M metres a radian.
The search is bounded by a count of clearance tests, not by a time: the same problem gives
the same path on any machine and under any load, so a re-planned flight is the same flight
(`pollination_flight.flight_id`). Metres and radians, bed frame.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from flowerpose.hardware.kinematics import HeadPose, joint_positions

#: Metres of head motion one radian of yaw or pitch counts for in a path's length and in the
#: spacing of its checks: the housings and the pollinator reach about 0.1 m from the axes.
ANGLE_LEVER_M = 0.1

#: Seconds after which a search ends whatever its count: only one that has stopped testing
#: states gets there (a few thousand tests take a second or two).
STALL_S = 60.0

#: Share of the search's clearance tests the path simplifier may spend after a path is found.
SIMPLIFY_SHARE = 0.25


def joint_state(pose: HeadPose) -> np.ndarray:
    """(5,) gantry x, y, z (metres, bed frame) and the servos' yaw and pitch (radians) of a
    single pose."""
    joints = joint_positions(pose)
    return np.concatenate([pose.gantry, joints[3:]])


def pose_of(states: np.ndarray) -> HeadPose:
    """The head poses of (5,) or (N, 5) joint states (`joint_state`)."""
    states = np.asarray(states, np.float64)
    return HeadPose(states[..., :3], states[..., 3], states[..., 4])


def plan_path(start: HeadPose, goal: HeadPose, clear: Callable[[HeadPose], bool],
              lower: np.ndarray, upper: np.ndarray, checks: int, step_m: float,
              seed: int = 0) -> list[HeadPose] | None:
    """A path from `start` to `goal` (single poses) whose every state, at `step_m` along each
    straight segment, passes `clear` (a pose -> whether it keeps clear), within the joint
    bounds `lower`..`upper` ((5,) each, as `joint_state`), spending at most `checks`
    clearance tests on the search and SIMPLIFY_SHARE more on shortening it. Returns the
    waypoints after the start, the last `goal`; None where none is found."""
    from ompl import base as ob
    from ompl import geometric as og
    from ompl import util as ou

    scale = np.array([1.0, 1.0, 1.0, ANGLE_LEVER_M, ANGLE_LEVER_M])
    low, high = np.asarray(lower, np.float64) * scale, np.asarray(upper, np.float64) * scale
    ends = np.array([joint_state(start), joint_state(goal)]) * scale
    if np.any(ends < low - 1e-9) or np.any(ends > high + 1e-9):
        return None
    if not (clear(start) and clear(goal)):  # OMPL would search on for a valid end
        return None
    ou.setLogLevel(ou.LOG_NONE)  # OMPL says every search on stderr; what matters is returned
    ou.RNG.setSeed(int(seed) + 1)  # OMPL's seeds must be positive
    space = ob.RealVectorStateSpace(5)
    bounds = ob.RealVectorBounds(5)
    for k in range(5):
        bounds.setLow(k, float(low[k]))
        bounds.setHigh(k, float(high[k]))
    space.setBounds(bounds)
    spent = [0]

    def valid(state) -> bool:
        spent[0] += 1
        values = np.array([state[k] for k in range(5)]) / scale
        return bool(clear(pose_of(values)))

    setup = og.SimpleSetup(space)
    setup.setStateValidityChecker(valid)
    info = setup.getSpaceInformation()
    info.setStateValidityCheckingResolution(step_m / space.getMaximumExtent())
    states = []
    for values in ends:
        state = space.allocState()
        for k in range(5):
            state[k] = float(values[k])
        states.append(state)
    setup.setStartAndGoalStates(states[0], states[1])
    setup.setPlanner(og.RRTConnect(info))
    # The count decides; the clock only stops a search that stopped testing states.
    deadline = time.monotonic() + STALL_S
    search = ob.PlannerTerminationCondition(
        lambda: spent[0] >= checks or time.monotonic() > deadline)
    if not setup.solve(search) or not setup.haveExactSolutionPath():
        return None
    budget = spent[0] + int(SIMPLIFY_SHARE * checks)
    setup.simplifySolution(ob.PlannerTerminationCondition(
        lambda: spent[0] >= budget or time.monotonic() > deadline))
    path = setup.getSolutionPath()
    waypoints = np.array([[path.getState(i)[k] for k in range(5)]
                          for i in range(1, path.getStateCount() - 1)]).reshape(-1, 5) / scale
    return [*(pose_of(w) for w in waypoints), goal]
