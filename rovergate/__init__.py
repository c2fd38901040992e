"""rovergate: closed-loop 3D active mapping by a rover with learned occupancy, over Zenoh.

This package is the base every other one builds on, and it imports none of them: key
expressions (:mod:`rovergate.keys`), message types and their CDR codec
(:mod:`rovergate.messages`), the plain data types that module logic takes and returns
(:mod:`rovergate.types`), the configuration tree (:mod:`rovergate.config`), the graph of
modules and topics (:mod:`rovergate.graph`), the Zenoh session helper and the node runtime
(:mod:`rovergate.node`). Scripts run missions with ``from mission import Mission``
(:mod:`mission.script`).
"""

__version__ = "0.1.0"
