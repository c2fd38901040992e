"""The run's outputs: metrics.json, coverage.csv, coverage.png and a top-down map picture."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from mission.scoring.record import MissionRecord  # noqa: E402
from planner.planner import planner_name  # noqa: E402
from rover_sim.overview import SURFACE_CMAP  # noqa: E402
from rovergate.config import MissionConfig  # noqa: E402


def _num(v: float | None) -> str:
    return "" if v is None else repr(v)


def _conditions(cfg: MissionConfig, record: MissionRecord) -> str:
    """The condition a run ran under, or each with the step it began at when a ground command
    changed it (``obs, gated from step 40``)."""
    if len(record.conditions) < 2:
        return record.conditions[0][1] if record.conditions else cfg.condition
    first, *rest = record.conditions
    return ", ".join([first[1], *(f"{c} from step {s}" for s, c in rest)])


def write_report(cfg: MissionConfig, record: MissionRecord, out: Path, plots: bool = True
                 ) -> dict:
    """Write every output file of a run into ``out`` (``plots``: with its two pictures);
    returns the metrics."""
    out.mkdir(parents=True, exist_ok=True)
    metrics = record.metrics()
    metrics.update(scene=cfg.scene.name, platform=cfg.platform, start=cfg.start, seed=cfg.seed,
                   condition=cfg.condition, planner=planner_name(cfg),
                   conditions=[list(c) for c in record.conditions],
                   d_scene_m=cfg.scene.d_scene_m,
                   tau_m=cfg.tau_m)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    with open(out / "coverage.csv", "w", newline="") as f:
        w = csv.writer(f)
        # One row per pose t; the motion columns describe the motion that led to pose t.
        # The decision columns describe the step that chose that motion (step t-1).
        w.writerow(["step", "coverage", "collided", "collision_class", "untraversable",
                    "min_clearance_m", "path_length_m", "pose_error_m", "stuck",
                    "fp_gain_share", "rejected_by_fp"])
        stuck = record.stuck()
        for t, c in enumerate(record.coverage):
            e = record.executions[t - 1] if 0 < t <= len(record.executions) else None
            motion = ([int(e.collided), record.collision_class[t - 1] or "",
                       int(e.untraversable), repr(e.min_clearance_m), repr(e.path_length_m),
                       repr(e.pose_error_m)] if e else [""] * 6)
            decision = ([_num(record.fp_gain_share[t - 1]), _num(record.rejected_by_fp[t - 1])]
                        if 0 < t <= len(record.fp_gain_share) else ["", ""])
            w.writerow([t, repr(c), *motion, int(stuck[t]) if t < len(stuck) else "",
                        *decision])
    if not plots:
        return metrics

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(range(len(record.coverage)), record.coverage, lw=2)
    ax.set(xlabel="planning step", ylabel="surface coverage", ylim=(0, 1),
           title=f"{cfg.scene.name}/{cfg.start}, {_conditions(cfg, record)}: final "
                 f"{metrics['final_coverage']:.3f}, AUC {metrics['auc']:.3f}")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "coverage.png", dpi=120)
    plt.close(fig)

    fig = topdown_figure(cfg, record)
    fig.savefig(out / "map_topdown.png", dpi=120)
    plt.close(fig)
    return metrics


def topdown_figure(cfg: MissionConfig, record: MissionRecord):
    """The top-down map: S_T coloured by height, the platform's path with its start and end,
    and its collisions by class; the legend below the map, where it hides nothing."""
    fig, ax = plt.subplots(figsize=(6, 7))
    ax.set_facecolor("white")  # unseen space; the surface's colours never reach white
    s = record.surface_xyz
    if len(s):
        sc = ax.scatter(s[:, 0], s[:, 1], c=s[:, 2], s=0.3, cmap=SURFACE_CMAP)
        fig.colorbar(sc, ax=ax, label="z (m)", shrink=0.7)
    vehicle = cfg.platform
    if record.base_xy:
        xy = list(zip(*record.base_xy, strict=True))
        ax.plot(xy[0], xy[1], "-o", color="crimson", ms=2, lw=1.2, label=f"{vehicle} path",
                zorder=3)
        ax.plot(*record.base_xy[0], "^", color="black", mfc="yellow", ms=10, mew=1.5,
                label="start", zorder=4)
        ax.plot(*record.base_xy[-1], "s", color="black", mfc="deepskyblue", ms=9, mew=1.5,
                label="end", zorder=4)
    for cls, marker in (("planner-fault", "rx"), ("unseen-geometry", "mx")):
        hits = [record.base_xy[i + 1] for i, k in enumerate(record.collision_class)
                if k == cls and i + 1 < len(record.base_xy)]
        if hits:
            ax.plot(*zip(*hits, strict=True), marker, ms=10, mew=2,
                    label=f"collision ({cls})", zorder=5)
    b = cfg.scene.bounds_m
    ax.set(xlim=(b[0], b[3]), ylim=(b[1], b[4]), aspect="equal", xlabel="x (m)", ylabel="y (m)",
           title=f"observed surface S_T (top-down) and {vehicle} path")
    # Below the map, not on it: a legend inside the axes hid the start and part of the path.
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=3, fontsize=8,
              frameon=False)
    fig.tight_layout()
    return fig
