"""Write a mesh of a rocky site (a PLY file) to try the rover on a scene of your own.

Uneven ground (a few metres of relief over 30 m, as smooth noise) strewn with rocks: 60
boulders from 0.2 m (the rover drives over the smallest) to 1.2 m across, their sizes and
places drawn from ``--seed``. The mesh is z-up in metres, as `rovergate run --scene FILE`
reads it by default.

Usage: .venv/bin/python examples/rocky_site.py rocky_site.ply [--seed 0]
       .venv/bin/rovergate run --scene rocky_site.ply --condition learned --steps 60
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import trimesh


def rocky_site(seed: int = 0, size_m: float = 30.0, rocks: int = 60) -> trimesh.Trimesh:
    rng = np.random.default_rng(seed)
    xs = np.linspace(-size_m / 2, size_m / 2, 121)
    X, Y = np.meshgrid(xs, xs)
    Z = np.zeros_like(X)
    for _ in range(6):  # smooth relief: a few broad bumps and hollows
        cx, cy = rng.uniform(-size_m / 2, size_m / 2, 2)
        w, h = rng.uniform(4.0, 9.0), rng.uniform(-0.8, 0.8)
        Z += h * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / (2 * w * w))
    V = np.c_[X.ravel(), Y.ravel(), Z.ravel()]
    n = len(xs)
    j, i = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (j * n + i).ravel()
    F = np.concatenate([np.c_[a, a + 1, a + n], np.c_[a + 1, a + n + 1, a + n]])
    parts = [trimesh.Trimesh(V, F, process=False)]
    for _ in range(rocks):
        r = rng.uniform(0.1, 0.6)
        x, y = rng.uniform(-size_m / 2 + 2, size_m / 2 - 2, 2)
        rock = trimesh.creation.icosphere(subdivisions=1, radius=r)
        rock.apply_scale([1.0, rng.uniform(0.7, 1.3), rng.uniform(0.5, 0.9)])
        z = float(np.interp(x, xs, Z[np.argmin(np.abs(xs - y))]))
        rock.apply_translation([x, y, z + 0.1 * r])
        parts.append(rock)
    return trimesh.util.concatenate(parts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rocky_site(args.seed).export(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
