"""The pictures a mission and the scene listing draw say what they show."""

from __future__ import annotations

import numpy as np
import pytest

from rovergate.config import MissionConfig


def mission(platform: str) -> MissionConfig:
    cfg = MissionConfig()
    cfg.platform = platform
    cfg.scene.bounds_m = (-10.0, -10.0, -1.0, 10.0, 10.0, 5.0)
    cfg.scene.d_scene_m = 30.0
    return cfg


def ground(spacing: float = 0.15) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(-9.5, 9.5, spacing), np.arange(-9.5, 9.5, spacing))
    return np.c_[xs.ravel(), ys.ravel(), np.zeros(xs.size)].astype(np.float32)


@pytest.mark.parametrize("platform", ["flyer", "rover"])
def test_the_topdown_map_names_the_platform_and_its_legend_hides_nothing(platform):
    """Issue 17, part 5: the map said "rover path" for the flyer too, its legend sat on the
    map over the start, high ground had the colour of unseen space, and it had no end."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import to_rgb

    from mission.scoring.record import MissionRecord
    from mission.scoring.report import topdown_figure
    cfg = mission(platform)
    record = MissionRecord()
    record.base_xy = [(-9.0, 9.0), (-5.0, 5.0), (0.0, 0.0)]
    record.collision_class = [None, "unseen-geometry"]
    record.surface_xyz = ground()[::50] + np.array([0, 0, 1], np.float32) * np.linspace(
        0, 20, len(ground()[::50]), dtype=np.float32)[:, None]  # heights 0 to 20 m
    fig = topdown_figure(cfg, record)
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels[:3] == [f"{platform} path", "start", "end"]
    assert "collision (unseen-geometry)" in labels
    assert ax.get_title().endswith(f"{platform} path")
    fig.canvas.draw()
    legend, axes = ax.get_legend().get_window_extent(), ax.get_window_extent()
    assert legend.y1 <= axes.y0  # below the map, not on it
    # No height is drawn in white or near it (unseen space is white).
    colours = ax.collections[0].get_facecolors()[:, :3]
    assert colours.min(axis=1).max() < 0.9 and to_rgb(ax.get_facecolor()) == (1.0, 1.0, 1.0)
    plt.close(fig)
