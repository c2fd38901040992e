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


def _rrt_connect(space, read: Callable, write: Callable, start, goal,
                 is_free: Callable[..., bool], max_checks: int,
                 resolution_m: float) -> list | None:
    """The straight motion if it is free, else RRT-Connect in ``space`` (bounds set), stopped
    after ``max_checks`` validity checks. Every state of the path after ``start`` is checked
    (``resolution_m`` apart along it); ``start`` itself is not, so that a platform the map
    now blocks where it stands can leave by a motion that is free everywhere else.

    ``read(state)`` gives a tuple from an OMPL state, ``write(state, values)`` sets one.
    """
    ss = og.SimpleSetup(space)
    checks = [0]
    s, g = space.allocState(), space.allocState()
    write(s, start)
    write(g, goal)
    here = read(s)

    def valid(state) -> bool:
        values = read(state)
        if values == here:  # the current state is not judged: the platform is there
            return True
        checks[0] += 1
        return is_free(*values)

    ss.setStateValidityChecker(valid)
    si = ss.getSpaceInformation()
    si.setStateValidityCheckingResolution(resolution_m / space.getMaximumExtent())
    if not valid(g):
        return None  # (RRT-Connect would wait for a valid goal without checking anything)
    ss.setStartAndGoalStates(s, g)
    ss.setup()
    if si.checkMotion(s, g):
        # The straight motion is free (OMPL's discrete motion check at ``resolution_m``): it is
        # the shortest path, and what simplifying a tree's path would converge to.
        return [read(s), read(g)]
    ss.setPlanner(og.RRTConnect(si))
    ptc = ob.PlannerTerminationCondition(lambda: checks[0] >= max_checks)
    status = ss.solve(ptc)
    if not ss.haveExactSolutionPath() or "Exact" not in str(status):
        return None
    ss.simplifySolution()
    return [read(p) for p in ss.getSolutionPath().getStates()]


def _seed(seed: int) -> None:
    ou.RNG.setSeed(int(seed) % (2**31 - 1) + 1)  # before anything that draws an RNG seed


def plan_se2(start: SE2, goal: SE2, is_free: Callable[[float, float, float], bool],
             bounds_xy: tuple[float, float, float, float], seed: int, max_checks: int,
             resolution_m: float = 0.05) -> list[SE2] | None:
    """A collision-free SE(2) path from ``start`` to ``goal`` (both included), or None."""
    _seed(seed)
    space = ob.SE2StateSpace()
    bounds = ob.RealVectorBounds(2)
    bounds.setLow(0, bounds_xy[0])
    bounds.setLow(1, bounds_xy[1])
    bounds.setHigh(0, bounds_xy[2])
    bounds.setHigh(1, bounds_xy[3])
    space.setBounds(bounds)

    def write(state, pose: SE2) -> None:
        state.setX(pose[0])
        state.setY(pose[1])
        state.setYaw((pose[2] + np.pi) % (2 * np.pi) - np.pi)  # OMPL's SO(2) is [-pi, pi)

    return _rrt_connect(space, lambda st: (st.getX(), st.getY(), st.getYaw()), write, start,
                        goal, is_free, max_checks, resolution_m)


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
    _seed(seed)
    space = ob.RealVectorStateSpace(3)
    b = ob.RealVectorBounds(3)
    for i in range(3):
        b.setLow(i, bounds[i])
        b.setHigh(i, bounds[i + 3])
    space.setBounds(b)

    def write(state, p: XYZ) -> None:
        for i in range(3):
            state[i] = float(p[i])

    return _rrt_connect(space, lambda st: (st[0], st[1], st[2]), write, start, goal, is_free,
                        max_checks, resolution_m)
