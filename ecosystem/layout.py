"""The Foxglove layout of the live view, built with ``foxglove.layouts`` from the graph's topics.

``python -m ecosystem.layout > docs/foxglove-layout.json`` writes the committed layout (a test
checks that it is this one). In Foxglove: Layouts, Import from file.

- a 3D panel in frame ``map``, following ``base_link``: the scene's mesh, the observed
  surface S_t (grey), the learned prediction (orange), the planner-facing map coloured by
  its ``source`` field (0 observed, 1 predicted, 2 oracle false negative, 3 truth; turbo
  colours from blue to red), the rover's traversability map (unknown, clear, obstacle), the
  planned path and the camera's pose;
- the depth image (turbo colours, near to far), and the rover's two hazard cameras';
- coverage against the step (``/rover/mission/status``'s ``coverage``);
- the mission status as it comes (step, state, condition, collisions).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import foxglove.layouts as fl

from ecosystem.live_view import scene_topic
from rovergate.keys import Keys


def layout(namespace: str = "rover") -> fl.Layout:
    keys = Keys(namespace)

    def topic(name: str) -> str:
        return "/" + keys.key(name)

    three_d = fl.ThreeDeePanel(title="map", config=fl.ThreeDeeConfig(
        fixed_frame="map", follow_tf="base_link", follow_mode="follow-position",
        topics={
            scene_topic(namespace): fl.BaseRendererSceneUpdateTopicSettings(visible=True),
            topic("surface"): fl.BaseRendererPointCloudTopicSettings(
                visible=True, point_size=2, color_mode="flat", flat_color="#9a9a9a"),
            topic("predicted"): fl.BaseRendererPointCloudTopicSettings(
                visible=False, point_size=4, color_mode="flat", flat_color="#ff8c00"),
            topic("planner_map"): fl.BaseRendererPointCloudTopicSettings(
                visible=True, point_size=4, color_mode="colormap", color_map="turbo",
                color_field="source", min_value=0, max_value=3),
            topic("traversability"): fl.BaseRendererRosOccupancyGridTopicSettings(
                visible=True),
            topic("path"): fl.BaseRendererPosesTopicSettings(visible=True, type="line",
                                                               line_width=0.08),
            topic("pose"): fl.BaseRendererPoseTopicSettings(visible=True, type="arrow"),
        }))
    depth = fl.ImagePanel(title="depth", config=fl.ImageConfig(
        image_mode=fl.ImageModeConfig(image_topic=topic("depth"), color_mode="colormap",
                                      color_map="turbo")))
    hazcams = fl.SplitContainer(direction="row", items=[
        fl.SplitItem(content=fl.ImagePanel(title=f"hazcam {end}", config=fl.ImageConfig(
            image_mode=fl.ImageModeConfig(image_topic=topic(f"hazcam_{end}"),
                                          color_mode="colormap", color_map="turbo"))))
        for end in ("front", "rear")])
    coverage = fl.PlotPanel(title="coverage", config=fl.PlotConfig(paths=[
        fl.PlotSeries(value=f"{topic('status')}.coverage", label="coverage",
                      timestamp_method="headerStamp")]))
    status = fl.RawMessagesPanel(title="mission status", config=fl.RawMessagesConfig(
        topic_path=topic("status")))
    right = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(proportion=2, content=depth), fl.SplitItem(content=hazcams),
        fl.SplitItem(content=coverage),
        fl.SplitItem(content=status)])
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=2, content=three_d), fl.SplitItem(content=right)]))


def layout_json(namespace: str = "rover") -> str:
    import json
    return json.dumps(json.loads(layout(namespace).to_json()), indent=2) + "\n"


def picture(bag: Path, out: Path, namespace: str = "rover") -> None:
    """What the layout's panels show, drawn with matplotlib from a recorded mission's bag
    (the last planner map, surface, traversability map, path, depth image, hazard-camera
    images and status; the coverage of every status): a picture for the manual where the
    Foxglove app cannot run."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from rosbags.rosbag2 import Reader

    from rovergate.graph import TOPICS
    from rovergate.messages import decode
    from rovergate.streams import StreamDecoder
    keys = Keys(namespace)
    wanted = {"/" + keys.key(t): t for t in ("planner_map", "surface", "base_pose", "depth",
                                              "status", "traversability", "hazcam_front",
                                              "hazcam_rear")}
    last: dict[str, Any] = {}
    decoders = {t: StreamDecoder(t) for t in ("planner_map", "surface")}
    coverage: list[tuple[int, float]] = []
    track: list[np.ndarray] = []
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic in wanted]
        for conn, _, data in reader.messages(connections=conns):
            topic = wanted[conn.topic]
            if topic == "status":
                status = decode("status", bytes(data))[1]
                if status.state == "running":
                    coverage.append((status.step, status.coverage))
                last["status"] = status
            elif topic == "base_pose":
                track.append(decode("base_pose", bytes(data))[1].position[:2])
            elif topic in decoders:  # an incremental map: every message, in order
                for whole_step, whole in decoders[topic].offer(decode(topic, bytes(data))[1]):
                    last[topic] = (whole_step, whole)
            else:
                last[topic] = bytes(data)
    map_step, planner_map = last["planner_map"]
    planner = planner_map.points
    surface = last["surface"][1]
    step, depth = decode("depth", last["depth"])
    status = last["status"]
    hazcams = {end: decode(f"hazcam_{end}", last[f"hazcam_{end}"])
               for end in ("front", "rear") if f"hazcam_{end}" in last}
    hazcams = {end: image for end, image in hazcams.items() if image[1].size}
    trav = decode("traversability", last["traversability"]) if "traversability" in last \
        else None

    fig = plt.figure(figsize=(13, 7.5))
    grid = fig.add_gridspec(4, 3, width_ratios=(2.2, 0.6, 0.6),
                            height_ratios=(1.6, 1, 1, 0.55))
    ax = fig.add_subplot(grid[:, 0])
    ax.scatter(surface["x"], surface["y"], s=0.2, c="#9a9a9a", label="observed surface")
    sc = ax.scatter(planner["x"], planner["y"], s=1.5, c=planner["source"], cmap="turbo",
                    vmin=0, vmax=3, label="planner map (by source)")
    xy = np.array(track)
    ax.plot(xy[:, 0], xy[:, 1], "-", color="black", lw=1.5, label="base_link (from /tf)")
    ax.set(title=f"3D panel, from above: {TOPICS['planner_map'].suffix}, step "
                 f"{map_step}", xlabel="x (m)", ylabel="y (m)",
           aspect="equal")
    cb = fig.colorbar(sc, ax=ax, shrink=0.6, ticks=[0, 1, 2, 3])
    cb.ax.set_yticklabels(["observed", "predicted", "oracle FN", "truth"])
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=3, markerscale=6,
              frameon=False)
    ax = fig.add_subplot(grid[0, 1:])
    shown = np.where(np.isfinite(depth), depth, np.nan)
    ax.imshow(shown, cmap="turbo")
    ax.set(title=f"image panel: depth, step {step}", xticks=[], yticks=[])
    for col, end in enumerate(("front", "rear"), start=1):
        ax = fig.add_subplot(grid[1, col])
        ax.set(xticks=[], yticks=[])
        if end in hazcams:
            image = hazcams[end][1]
            ax.imshow(np.where(np.isfinite(image), image, np.nan), cmap="turbo")
            ax.set_title(f"hazcam {end}, step {hazcams[end][0]}", fontsize=9)
        else:
            ax.set_title(f"hazcam {end}: none", fontsize=9)
    ax = fig.add_subplot(grid[2, 1])
    ax.set(xticks=[], yticks=[])
    if trav is not None and trav[1].cells.size:
        g = trav[1]
        h, w = g.cells.shape
        x0, y0 = g.origin_xy
        shade = np.full((h, w, 3), 0.75)
        shade[g.cells == 0] = (0.55, 0.85, 0.55)
        shade[g.cells == 100] = (0.85, 0.15, 0.15)
        ax.imshow(shade, origin="lower", interpolation="nearest",
                  extent=(x0, x0 + w * g.resolution_m, y0, y0 + h * g.resolution_m))
        ax.plot(xy[:, 0], xy[:, 1], "-", color="black", lw=1)
        ax.plot(*xy[-1], "o", color="black", ms=4)
        ax.set(xlim=(x0, x0 + w * g.resolution_m), ylim=(y0, y0 + h * g.resolution_m))
        ax.set_title(f"traversability, step {trav[0]}\ngreen clear, red obstacle, grey "
                     "unknown", fontsize=8)
    else:
        ax.set_title("traversability: none", fontsize=9)
    ax = fig.add_subplot(grid[2, 2])
    steps, cov = zip(*coverage, strict=True)
    ax.plot(steps, cov, lw=2)
    ax.set(title="plot panel: coverage", xlabel="step", ylim=(0, 1))
    ax.grid(alpha=0.3)
    ax = fig.add_subplot(grid[3, 1:])
    ax.axis("off")
    ax.text(0, 0.5, f"mission status: step {status.step}/{status.steps_total}, "
                    f"{status.state}\ncondition {status.condition}, coverage "
                    f"{status.coverage:.3f}, collisions {status.collisions}",
            family="monospace", va="center", fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main() -> None:
    import argparse
    ap = argparse.ArgumentParser(description="Print the live view's Foxglove layout (JSON), "
                                 "or draw what its panels show from a recorded mission.")
    ap.add_argument("--picture", type=Path, help="write the picture here (needs --bag)")
    ap.add_argument("--bag", type=Path, help="a mission's bag (OUT/bag)")
    args = ap.parse_args()
    if args.picture:
        if not args.bag:
            ap.error("--picture needs --bag OUT/bag")
        picture(args.bag, args.picture)
    else:
        print(layout_json(), end="")


if __name__ == "__main__":
    main()
