"""rovergate: closed-loop 3D active mapping by a rover with learned occupancy, over Zenoh.

This package holds what every process needs: key expressions (:mod:`rovergate.keys`), message
types and their CDR codec (:mod:`rovergate.messages`), the plain data types that module logic
takes and returns (:mod:`rovergate.types`), the configuration tree (:mod:`rovergate.config`),
the Zenoh session helper and the node runtime (:mod:`rovergate.node`); and, for scripts,
``from rovergate import Mission`` (:mod:`mission.script`).
"""

__version__ = "0.1.0"

__all__ = ["Mission", "MissionResult"]


def __getattr__(name: str):
    """``from rovergate import Mission``: the mission API (:mod:`mission.script`), imported
    on use so that a module process never loads it."""
    if name in __all__:
        from mission import script
        return getattr(script, name)
    raise AttributeError(f"module 'rovergate' has no attribute {name!r}")
