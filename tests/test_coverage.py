"""Coverage and AUC on hand-made cases."""

from __future__ import annotations

import numpy as np
import pytest

from mission.scoring.coverage import CoverageEvaluator, auc


def test_coverage_counts_samples_within_tau():
    samples = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], dtype=np.float32)
    ev = CoverageEvaluator(samples, tau_m=0.2)
    assert ev.update(np.array([[0.1, 0, 0]], dtype=np.float32)) == 0.25
    grown = np.array([[0.1, 0, 0], [2.15, 0, 0], [3.5, 0, 0]], dtype=np.float32)
    assert ev.update(grown) == 0.5
    assert ev.update(grown) == 0.5  # nothing new, nothing changes


def test_coverage_starts_over_when_the_surface_is_not_an_extension():
    samples = np.array([[0, 0, 0], [1, 0, 0]], dtype=np.float32)
    ev = CoverageEvaluator(samples, tau_m=0.2)
    ev.update(np.array([[0, 0, 0], [1, 0, 0]], dtype=np.float32))
    assert ev.update(np.array([[1, 0, 0]], dtype=np.float32)) == 0.5


def test_auc_is_the_normalised_trapezoid():
    assert auc([0.0, 1.0]) == 0.5
    assert auc([0.2, 0.2, 0.2]) == pytest.approx(0.2)
    assert auc([0.0, 0.5, 1.0]) == pytest.approx(0.5)
