"""Nearest-neighbour queries on point sets that are rebuilt every step.

:func:`kdtree` is scipy's k-d tree built without the median balancing and node compaction
that suit long-lived trees: its queries return exactly the same distances, and it builds two
to three times faster, which matters for the maps the gate and the planner rebuild each step.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def kdtree(points: np.ndarray) -> cKDTree:
    """A k-d tree of (N, 3) ``points`` for one step's queries."""
    return cKDTree(points, balanced_tree=False, compact_nodes=False)
