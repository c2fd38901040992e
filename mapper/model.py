"""The learned occupancy completion: a 3-D U-Net over a local window of the mapper's voxel grid.

Input: a window of :class:`mapper.grid.OccupancyGrid` around the camera, one-hot occupied /
free / unknown, plus each voxel's offset from the camera (x, y, z and horizontal range) and a
constant (8 channels; 8 also keeps the first convolution on oneDNN's fast path, which 4 input
channels miss). Output: for every voxel of the window, the logit that the true surface passes
through it. The camera poses enter twice: the free channel is the space the cameras looked
through from where they stood, and the offsets place the current camera.

Why this architecture: the mapper already keeps its evidence as voxels, so a dense 3-D
convolution consumes it directly, with no point sampling or feature volume to build. A U-Net
with three downsamplings sees the whole window (a 3.2 m cell at the coarsest level, about 25 m
of context), which is what continuing terrain and the backs of rocks needs, while its last
layers stay at full resolution for precise surfaces. Its pass over one window takes about
35 ms on one core of an AVX2 CPU (OpenVINO, float32; ``benchmarks/bench_mapper.py``), and one
window per step covers what the camera can see.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import torch
from torch import nn

from mapper.grid import FREE, OCCUPIED, GridSpec
from rovergate.errors import CheckpointError

IN_CHANNELS = 8
#: A vertical run of at most this many predicted voxels is one surface crossing its column (see
#: OccupancyPredictor.predicted); a longer one is a wall or a steep face.
SURFACE_RUN_VOXELS = 3


@dataclass(frozen=True)
class WindowSpec:
    """The model's window: its voxel size, its size in voxels, and where the camera sits in
    it (centred in x and y, ``below`` voxels above its floor)."""

    voxel_m: float = 0.4
    size: tuple[int, int, int] = (64, 64, 32)
    below: int = 20

    def start(self, spec: GridSpec, camera_m: np.ndarray) -> np.ndarray:
        """(3,) int64 grid index of the window's first voxel for a camera position."""
        ijk, _ = spec.index(np.asarray(camera_m, np.float64)[None])
        half = np.array([self.size[0] // 2, self.size[1] // 2, self.below])
        return ijk[0] - half


def overlap(start: np.ndarray, size: tuple[int, int, int], shape: tuple[int, ...]
            ) -> tuple[tuple[slice, ...], tuple[slice, ...]] | None:
    """Where a window at ``start`` of ``size`` meets a volume of ``shape``: (the slices in the
    volume, the slices in the window), or None where they do not meet."""
    lo = np.maximum(start, 0)
    hi = np.minimum(start + np.asarray(size), shape)
    if np.any(hi <= lo):
        return None
    in_volume = tuple(slice(a, b) for a, b in zip(lo, hi, strict=True))
    in_window = tuple(slice(a - s, b - s) for a, b, s in zip(lo, hi, start, strict=True))
    return in_volume, in_window


def crop(volume: np.ndarray, start: np.ndarray, size: tuple[int, int, int],
         fill: float | int = 0) -> np.ndarray:
    """The ``size`` block of ``volume`` from index ``start``; outside it reads ``fill``."""
    out = np.full(size, fill, dtype=volume.dtype)
    where = overlap(start, size, volume.shape)
    if where is not None:
        out[where[1]] = volume[where[0]]
    return out


def encode_state(state: np.ndarray) -> np.ndarray:
    """(3, X, Y, Z) float32: the first channels of :func:`encode` (occupied, free, unknown)."""
    out = np.empty((3, *state.shape), dtype=np.float32)
    out[0] = (state & OCCUPIED) != 0
    out[1] = state == FREE
    out[2] = state == 0
    return out


def encode(state: np.ndarray, below: int) -> np.ndarray:
    """(8, X, Y, Z) float32 network input from an (X, Y, Z) uint8 state window whose camera
    voxel is (X // 2, Y // 2, below)."""
    nx, ny, nz = state.shape
    out = np.empty((IN_CHANNELS, nx, ny, nz), dtype=np.float32)
    out[:3] = encode_state(state)
    x = (np.arange(nx, dtype=np.float32) - nx // 2) / 16.0
    y = (np.arange(ny, dtype=np.float32) - ny // 2) / 16.0
    out[3] = ((np.arange(nz, dtype=np.float32) - below) / 16.0)[None, None, :]
    out[4] = x[:, None, None]
    out[5] = y[None, :, None]
    out[6] = np.sqrt(x[:, None] ** 2 + y[None, :] ** 2)[:, :, None]
    out[7] = 1.0
    return out


def _conv(c_in: int, c_out: int, k: int = 3, stride: int = 1, dilation: int = 1) -> nn.Module:
    pad = 0 if stride > 1 else dilation * (k // 2)
    return nn.Sequential(nn.Conv3d(c_in, c_out, k, stride, pad, dilation), nn.ReLU(inplace=True))


class OccupancyNet(nn.Module):
    """3-D U-Net: (B, 4, X, Y, Z) window encoding -> (B, 1, X, Y, Z) surface logits.

    X, Y and Z must be multiples of 8.
    """

    def __init__(self, widths: tuple[int, int, int, int] = (12, 24, 48, 64)) -> None:
        super().__init__()
        c0, c1, c2, c3 = widths
        self.stem = _conv(IN_CHANNELS, c0)
        self.down1 = nn.Sequential(_conv(c0, c1, 2, 2), _conv(c1, c1))
        self.down2 = nn.Sequential(_conv(c1, c2, 2, 2), _conv(c2, c2), _conv(c2, c2, dilation=2))
        self.down3 = nn.Sequential(_conv(c2, c3, 2, 2), _conv(c3, c3), _conv(c3, c3, dilation=2))
        self.up3 = nn.ConvTranspose3d(c3, c2, 2, 2)
        self.fuse2 = _conv(2 * c2, c2)
        self.up2 = nn.ConvTranspose3d(c2, c1, 2, 2)
        self.fuse1 = _conv(2 * c1, c1)
        self.up1 = nn.ConvTranspose3d(c1, c0, 2, 2)
        self.head = nn.Sequential(_conv(2 * c0, 16, k=1), nn.Conv3d(16, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f0 = self.stem(x)
        f1 = self.down1(f0)
        f2 = self.down2(f1)
        f3 = self.down3(f2)
        g2 = self.fuse2(torch.cat([self.up3(f3), f2], 1))
        g1 = self.fuse1(torch.cat([self.up2(g2), f1], 1))
        return self.head(torch.cat([self.up1(g1), f0], 1))


# ----------------------------------------------------------------------------- checkpoint

CHECKPOINT_NAME = "occupancy.pt"
REBUILD_HINT = "rebuild it with `rovergate train --out {path}` (about 35 minutes on a 2-core CPU)"


def shipped_checkpoint() -> Path:
    """Where the package keeps its trained weights."""
    return Path(str(resources.files("mapper") / "weights" / CHECKPOINT_NAME))


@dataclass
class Checkpoint:
    """Trained weights and what is needed to use them."""

    model: OccupancyNet
    window: WindowSpec
    meta: dict
    path: Path


def save_checkpoint(path: Path, model: OccupancyNet, window: WindowSpec, meta: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    meta = json.loads(json.dumps(meta, default=str))  # plain types: loads with weights_only
    torch.save({"format": 1, "window": asdict(window), "meta": meta, "state_dict": state}, path)


def load_checkpoint(path: Path | None = None) -> Checkpoint:
    """The checkpoint at ``path`` (default: the shipped one), ready for inference on the CPU.

    A missing or unreadable file raises CheckpointError with one line saying how to rebuild it.
    """
    path = Path(path) if path is not None else shipped_checkpoint()
    if not path.is_file():
        raise CheckpointError(f"the occupancy model checkpoint {path} is missing; "
                              f"{REBUILD_HINT.format(path=path)}")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
        window = WindowSpec(**{k: tuple(v) if isinstance(v, list) else v
                               for k, v in blob["window"].items()})
        model = OccupancyNet()
        model.load_state_dict(blob["state_dict"])
    except Exception as e:  # a truncated zip, a pickle error, missing or misshaped tensors
        first_line = str(e).splitlines()[0][:120] if str(e) else ""
        raise CheckpointError(f"the occupancy model checkpoint {path} is corrupt "
                              f"({type(e).__name__}: {first_line}); "
                              f"{REBUILD_HINT.format(path=path)}") from None
    model.eval()
    return Checkpoint(model, window, dict(blob.get("meta", {})), path)


def file_sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def weights_sha256(model: nn.Module) -> str:
    """SHA-256 of the weights alone (every tensor's bytes, in state-dict order): what a
    reproduction must match, whatever timings the checkpoint's metadata records."""
    h = hashlib.sha256()
    for name, t in model.state_dict().items():
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


# ----------------------------------------------------------------------------- inference
