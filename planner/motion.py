"""Motion planning in SE(2) with OMPL (RRT-Connect), validity checked by a callable.

Determinism: OMPL's random generator is re-seeded before every query, and the query ends
after a fixed number of validity checks rather than after a time, so the same map and seed
give the same path on any machine load.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from ompl import base as ob
from ompl import geometric as og
from ompl import util as ou

ou.setLogLevel(ou.LogLevel.LOG_NONE)

SE2 = tuple[float, float, float]


def plan_se2(start: SE2, goal: SE2, is_free: Callable[[float, float, float], bool],
             bounds_xy: tuple[float, float, float, float], seed: int, max_checks: int,
             resolution_m: float = 0.05) -> list[SE2] | None:
    """A collision-free SE(2) path from ``start`` to ``goal`` (both included), or None."""
    ou.RNG.setSeed(int(seed) % (2**31 - 1) + 1)  # before anything that draws an RNG seed
    space = ob.SE2StateSpace()
    bounds = ob.RealVectorBounds(2)
    bounds.setLow(0, bounds_xy[0])
    bounds.setLow(1, bounds_xy[1])
    bounds.setHigh(0, bounds_xy[2])
    bounds.setHigh(1, bounds_xy[3])
    space.setBounds(bounds)
    ss = og.SimpleSetup(space)
    checks = [0]

    def valid(state) -> bool:
        checks[0] += 1
        return is_free(state.getX(), state.getY(), state.getYaw())

    ss.setStateValidityChecker(valid)
    si = ss.getSpaceInformation()
    si.setStateValidityCheckingResolution(resolution_m / space.getMaximumExtent())
    s, g = space.allocState(), space.allocState()
    for state, (x, y, yaw) in ((s, start), (g, goal)):
        state.setX(x)
        state.setY(y)
        state.setYaw((yaw + np.pi) % (2 * np.pi) - np.pi)  # OMPL's SO(2) is [-pi, pi)
    ss.setStartAndGoalStates(s, g)
    ss.setPlanner(og.RRTConnect(si))
    ptc = ob.PlannerTerminationCondition(lambda: checks[0] >= max_checks)
    status = ss.solve(ptc)
    if not ss.haveExactSolutionPath() or "Exact" not in str(status):
        return None
    ss.simplifySolution()
    path = ss.getSolutionPath()
    return [(p.getX(), p.getY(), p.getYaw()) for p in path.getStates()]


def path_length(path: list[SE2]) -> float:
    xy = np.array([p[:2] for p in path])
    return float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()) if len(xy) > 1 else 0.0


XYZ = tuple[float, float, float]


def plan_r3(start: XYZ, goal: XYZ, is_free: Callable[[float, float, float], bool],
            bounds: tuple[float, float, float, float, float, float], seed: int,
            max_checks: int, resolution_m: float = 0.05) -> list[XYZ] | None:
    """A collision-free path of positions from ``start`` to ``goal`` (both included), or None.

    The flyer's path: positions only; its view direction turns along the path (the planner
    interpolates it), which does not change what its sphere touches.
    """
    ou.RNG.setSeed(int(seed) % (2**31 - 1) + 1)
    space = ob.RealVectorStateSpace(3)
    b = ob.RealVectorBounds(3)
    for i in range(3):
        b.setLow(i, bounds[i])
        b.setHigh(i, bounds[i + 3])
    space.setBounds(b)
    ss = og.SimpleSetup(space)
    checks = [0]

    def valid(state) -> bool:
        checks[0] += 1
        return is_free(state[0], state[1], state[2])

    ss.setStateValidityChecker(valid)
    si = ss.getSpaceInformation()
    si.setStateValidityCheckingResolution(resolution_m / space.getMaximumExtent())
    s, g = space.allocState(), space.allocState()
    for state, p in ((s, start), (g, goal)):
        for i in range(3):
            state[i] = float(p[i])
    ss.setStartAndGoalStates(s, g)
    ss.setPlanner(og.RRTConnect(si))
    ptc = ob.PlannerTerminationCondition(lambda: checks[0] >= max_checks)
    status = ss.solve(ptc)
    if not ss.haveExactSolutionPath() or "Exact" not in str(status):
        return None
    ss.simplifySolution()
    return [(p[0], p[1], p[2]) for p in ss.getSolutionPath().getStates()]
