"""Coverage: the fraction of true surface samples with an observed point within tau."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


class CoverageEvaluator:
    """Incremental coverage of ground-truth surface samples by the observed surface S_t.

    S_t only grows and the mapper appends new voxels at the end, so each update looks up only
    the points added since the last one, in a k-d tree of the samples built once: the cost of
    a step follows what the step added, not the size of the scene.
    """

    def __init__(self, truth_samples: np.ndarray, tau_m: float) -> None:
        self.samples = np.asarray(truth_samples, dtype=np.float32)
        self.tau_m = tau_m
        self.covered = np.zeros(len(self.samples), dtype=bool)
        self._tree = cKDTree(self.samples) if len(self.samples) else None
        self._n_seen = 0

    def update(self, surface_xyz: np.ndarray) -> float:
        """Coverage after S_t = ``surface_xyz``; returns the covered fraction."""
        if len(surface_xyz) < self._n_seen:  # not an extension of the last S_t: start over
            self.covered[:] = False
            self._n_seen = 0
        new = np.asarray(surface_xyz[self._n_seen:], dtype=np.float64)
        self._n_seen = len(surface_xyz)
        if len(new) and self._tree is not None:
            hits = self._tree.query_ball_point(new, r=self.tau_m, return_sorted=False)
            idx = np.fromiter((i for h in hits for i in h), dtype=np.int64)
            self.covered[idx] = True
        return self.fraction

    @property
    def fraction(self) -> float:
        return float(self.covered.mean()) if len(self.covered) else 0.0


def auc(coverage: list[float] | np.ndarray) -> float:
    """Area under the per-step coverage curve over steps 0..T, normalised to [0, 1]."""
    c = np.asarray(coverage, dtype=np.float64)
    if len(c) < 2:
        return float(c[0]) if len(c) else 0.0
    return float(np.sum((c[1:] + c[:-1]) / 2.0) / (len(c) - 1))
