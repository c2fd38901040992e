"""`rovergate scenes`: list the scenes with their sizes and starts, and draw each of them.

The picture of a scene has two panels: a top-down map of its true surface coloured by height
with the box of interest and the five starts (arrows: the heading), and an oblique view
rendered by pybullet.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from rover_sim.bullet import pb
from rover_sim.catalog import catalog, load_scene
from rover_sim.scene import Scene
from rover_sim.world import add_scene
from rovergate.config import SceneConfig


def describe(scene: Scene, kind: str) -> list[str]:
    b = scene.bounds_m
    size = f"{b[3] - b[0]:.1f} x {b[4] - b[1]:.1f} x {b[5] - b[2]:.1f} m"
    lines = [f"{scene.name:<12} {kind:<10} {size:<24} d_scene {scene.d_scene_m:6.2f} m   "
             f"{scene.description}"]
    starts = "  ".join(f"{k}=({x:.1f}, {y:.1f}, {np.degrees(t):.0f}°)"
                       for k, (x, y, t) in scene.starts.items())
    lines.append(f"{'':<12} starts (x, y, heading): {starts}")
    return lines


#: The colours of a surface by height, in every picture (the scenes', a mission's map): none
#: white or near it, the colour of unseen space ("terrain" turns white at its top, so high
#: ground read as unseen).
SURFACE_CMAP = "viridis"
#: Gain on the rendered colours of the 3-D view.
BRIGHTEN = 1.25


def oblique_view(scene: Scene, width: int = 640, height: int = 400) -> np.ndarray:
    """(H, W, 3) uint8 RGB view of the scene from above one corner of its box of interest."""
    cid = pb.connect(pb.DIRECT)
    try:
        add_scene(cid, scene)
        b = np.array(scene.bounds_m)
        centre = (b[:3] + b[3:]) / 2
        eye = np.array([b[0], b[1], b[5]]) + np.array([-0.3, -0.3, 0.6]) * (b[3] - b[0])
        view = pb.computeViewMatrix(eye.tolist(), centre.tolist(), [0, 0, 1],
                                    physicsClientId=cid)
        proj = pb.computeProjectionMatrixFOV(50, width / height, 0.5, 400, physicsClientId=cid)
        # More ambient light than pybullet's default (the faces turned from the light were
        # near black), and a little stretch of what comes back.
        rgb = pb.getCameraImage(width, height, view, proj, renderer=pb.ER_TINY_RENDERER,
                                lightDirection=[-1, -0.5, 2], lightAmbientCoeff=0.75,
                                lightDiffuseCoeff=0.55, lightSpecularCoeff=0.05,
                                physicsClientId=cid)[2]
        img = np.asarray(rgb, dtype=np.uint8).reshape(height, width, 4)[..., :3]
        return np.clip(img.astype(np.float32) * BRIGHTEN, 0, 255).astype(np.uint8)
    finally:
        pb.disconnect(cid)


def render_overview(scene: Scene, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    pts = scene.surface_samples(25_000, seed=0)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13, 6), gridspec_kw={"width_ratios": [1, 1.3]})
    order = np.argsort(pts[:, 2])
    sc = ax.scatter(pts[order, 0], pts[order, 1], c=pts[order, 2], s=0.4, cmap=SURFACE_CMAP)
    fig.colorbar(sc, ax=ax, label="z (m)", shrink=0.8)
    for name, (x, y, t) in scene.starts.items():
        ax.annotate("", xy=(x + 1.5 * np.cos(t), y + 1.5 * np.sin(t)), xytext=(x, y),
                    arrowprops={"arrowstyle": "->", "color": "crimson", "lw": 2})
        ax.plot(x, y, "o", color="crimson", ms=6)
        ax.text(x + 0.4, y + 0.4, name, color="black", fontsize=12, weight="bold")
    b = scene.bounds_m
    ax.set(xlim=(b[0], b[3]), ylim=(b[1], b[4]), aspect="equal", xlabel="x (m)",
           ylabel="y (m)", title=f"{scene.name}: surface and starts (d_scene "
                                 f"{scene.d_scene_m:.2f} m)")
    ax2.imshow(oblique_view(scene))
    ax2.set_axis_off()
    ax2.set_title(scene.description)
    fig.tight_layout()
    fig.savefig(path, dpi=75)
    plt.close(fig)


@dataclass
class ScenesConfig:
    """List the scenes (or the named ones and mesh files), with sizes and starts."""

    names: tyro.conf.Positional[tuple[str, ...]] = ()
    """Scene names or mesh files (default: every registered scene)."""
    up_axis: str = "z"
    """Mesh files: their up axis."""
    scale: float = 1.0
    """Mesh files: metres per file unit."""
    render: Path | None = None
    """Write DIR/<scene>.png for each scene."""


def main(args: ScenesConfig) -> int:
    scenes = catalog()
    names = args.names or list(scenes)
    if args.render:
        args.render.mkdir(parents=True, exist_ok=True)
    for name in names:
        scene = load_scene(SceneConfig(name=name, up_axis=args.up_axis, scale=args.scale))
        kind = scenes[name].kind if name in scenes else "mesh file"
        print("\n".join(describe(scene, kind)), flush=True)
        if args.render:
            out = args.render / f"{scene.name}.png"
            render_overview(scene, out)
            print(f"{'':<12} picture: {out}", flush=True)
    return 0


