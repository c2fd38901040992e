"""rovergate: closed-loop 3D active mapping by a rover with learned occupancy, over Zenoh.

This package holds what every process needs: key expressions (:mod:`rovergate.keys`), message
types and their CDR codec (:mod:`rovergate.messages`), the plain data types that module logic
takes and returns (:mod:`rovergate.types`), the configuration tree (:mod:`rovergate.config`),
the Zenoh session helper and the node runtime (:mod:`rovergate.node`).
"""

__version__ = "0.1.0"
