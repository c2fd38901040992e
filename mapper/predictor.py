"""The learned occupancy at run time: the model's pass on the window around the camera, each
step, through one of its engines (:mod:`mapper.engines`), and what it predicted per voxel."""

from __future__ import annotations

import numpy as np
import torch

from mapper.engines import make_engine
from mapper.grid import OCCUPIED, OccupancyGrid
from mapper.model import SURFACE_RUN_VOXELS, Checkpoint, crop, overlap


def to_float16(values: np.ndarray) -> np.ndarray:
    """``values.astype(np.float16)`` of a float32 array, to the bit: both round to nearest,
    ties to even, but numpy converts the results that are float16 subnormals (the many
    probabilities under 6e-5 of empty space) one by one in software, some 3 ms a window, where
    torch uses the CPU's conversion instruction."""
    return torch.from_numpy(np.ascontiguousarray(values, dtype=np.float32)).to(
        torch.float16).numpy()


class OccupancyPredictor:
    """Runs the model on the window around the camera and keeps what it predicted, per voxel.

    Each step overwrites the window's voxels with the newest probabilities; voxels outside it
    keep their last prediction (0 where never predicted).
    """

    def __init__(self, checkpoint: Checkpoint, grid: OccupancyGrid,
                 precision: str = "float32", engine: str = "openvino") -> None:
        """``engine`` and ``precision``: the runtime and arithmetic of the model's pass
        (:mod:`mapper.engines`; missions take ``MapperConfig.engine`` and
        ``MapperConfig.precision``, OpenVINO in float32 by default). ``bfloat16`` runs it
        about 1.7 times faster on a CPU with native bfloat16 (AVX512-BF16 or AMX), and moves
        the numbers a little: on a mission's windows, probabilities by up to 0.012 to 0.016 and
        the 0.5 decision of about one covered voxel in 13,000. Without native support it is many
        times slower than float32 in torch, and refused by OpenVINO."""
        if abs(checkpoint.window.voxel_m - grid.spec.voxel_m) > 1e-9:
            raise ValueError("the grid's voxel size differs from the model's")
        self.engine = make_engine(checkpoint, engine, precision)
        self.window = checkpoint.window
        self.grid = grid
        self.probability = np.zeros(grid.spec.shape, dtype=np.float16)
        """(nx, ny, nz) float16 latest predicted occupancy probability of each voxel."""
        self.covered = np.zeros(grid.spec.shape, dtype=bool)
        """(nx, ny, nz) bool: voxels that have been inside a prediction window."""
        self._last: tuple[np.ndarray, np.ndarray] | None = None  # start and state predicted

    def update(self, camera_m: np.ndarray) -> None:
        """Predict the window around ``camera_m`` from the grid as it is now."""
        w = self.window
        start = w.start(self.grid.spec, camera_m)
        state = crop(self.grid.state, start, w.size)
        if (self._last is not None and np.array_equal(self._last[0], start)
                and np.array_equal(self._last[1], state)):
            # The same window holding the same grid as the last prediction (a platform that
            # could not move, looking at what it saw): the model would give the same numbers,
            # and they are in ``probability`` already.
            return
        self._last = (start, state)
        logits = self.engine(state)
        # The sigmoid in float64: numpy's exp takes another SIMD path on each CPU family, and
        # its float64 results differ by less than float16's rounding ever sees (its float32
        # ones would reach the float16 probabilities below AVX2).
        prob = to_float16(1.0 / (1.0 + np.exp(-logits.astype(np.float64))))
        where = overlap(start, w.size, self.grid.spec.shape)
        if where is not None:
            self.probability[where[0]] = prob[where[1]]
            self.covered[where[0]] = True

    def _at_least(self, threshold: float) -> np.ndarray:
        """(nx, ny, nz) bool: ``probability >= threshold``. The probabilities are sigmoid
        outputs in [0, 1] (never negative, never NaN), and the bit patterns of non-negative
        float16 numbers order as their values: where the threshold is a float16 number, its
        bits are compared, without float16 arithmetic (which numpy does in software)."""
        t16 = np.float16(threshold)
        if threshold > 0 and float(t16) == threshold:
            return self.probability.view(np.uint16) >= t16.view(np.uint16)
        return self.probability >= threshold

    def predicted(self, threshold: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
        """The prediction as surface points: (M, 3) float32 and their (M,) float32
        probabilities.

        Voxels at probability >= threshold, read column by column as vertical runs (voxels
        with a depth return join the runs). A surface crossing a column, as the ground does,
        fills one to three voxels of it (more where the model is unsure of its height): such a
        run becomes one point at the height where the probabilities of the run and of the
        voxels under and over it centre, or no point if a return already stands for it (S_t
        has that point). Longer runs are walls and steep faces: each of their voxels without a
        return is a point. Without this, the 0.4 m grid makes predicted ground one to three
        voxels thick, and its upper voxels stand higher over the lower ones than the rover's
        0.25 m ground clearance: the rover read predicted ground as obstacles and stood still.
        """
        observed = (self.grid.state & OCCUPIED) != 0
        predicted = self._at_least(threshold) & ~observed
        flat = np.flatnonzero(predicted | observed)  # C order: columns contiguous, k ascending
        if len(flat) == 0:
            return np.zeros((0, 3), np.float32), np.zeros(0, np.float32)
        ijk = np.stack(np.unravel_index(flat, predicted.shape), axis=1)  # np.argwhere, cheaper
        pred = predicted.reshape(-1)[flat]
        prob = self.probability.reshape(-1)[flat].astype(np.float64) * pred
        starts = np.r_[True, np.any(ijk[1:, :2] != ijk[:-1, :2], axis=1)
                       | (ijk[1:, 2] != ijk[:-1, 2] + 1)]
        run = np.cumsum(starts) - 1
        length = np.bincount(run)
        has_return = np.bincount(run, weights=~pred) > 0
        # Long runs: every predicted voxel.
        long_ = (length[run] > SURFACE_RUN_VOXELS) & pred
        pts = [self.grid.spec.centres(ijk[long_])]
        probs = [prob[long_]]
        # Short runs without a return: one point at the height where the probability of the
        # run and of the voxel under and over it centres (sub-voxel, as the surface is).
        short = (length <= SURFACE_RUN_VOXELS) & ~has_return
        first = np.flatnonzero(starts)[short]
        i, j, k0 = ijk[first, 0], ijk[first, 1], ijk[first, 2]
        run_length = length[short]
        nz = self.grid.spec.shape[2]
        w = np.zeros(len(first))
        wk = np.zeros(len(first))
        for dk in range(-1, SURFACE_RUN_VOXELS + 1):  # from the voxel under the run to over it
            k = k0 + dk
            use = (k >= 0) & (k < nz) & (dk <= run_length)
            p = np.where(use, self.probability[i, j, np.clip(k, 0, nz - 1)], 0.0)
            w += p
            wk += p * k
        k_surface = wk / np.maximum(w, 1e-12)
        centre = self.grid.spec.centres(ijk[first])
        centre[:, 2] += ((k_surface - k0) * self.grid.spec.voxel_m).astype(np.float32)
        pts.append(centre)
        probs.append(np.maximum.reduceat(prob, np.flatnonzero(starts))[short])
        return np.concatenate(pts), np.concatenate(probs).astype(np.float32)
