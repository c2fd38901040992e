"""The composition root: the ``rovergate`` command (:mod:`mission.cli`), one mission
(:mod:`mission.run`), mission files and the Python API (:mod:`mission.script`:
``from mission import Mission``), and the rooms they are built from: the mission runtime
(:mod:`mission.runtime`), the link to Earth (:mod:`mission.link`), scoring against ground
truth (:mod:`mission.scoring`) and the study (:mod:`mission.study`)."""

__all__ = ["Mission", "MissionResult"]


def __getattr__(name: str):
    """``from mission import Mission``: the mission API (:mod:`mission.script`), imported on
    use so that a module process, which imports this package, never loads it."""
    if name in __all__:
        from mission import script
        return getattr(script, name)
    raise AttributeError(f"module 'mission' has no attribute {name!r}")
