"""The Foxglove layout of the live view, built with ``foxglove.layouts`` from the graph's topics.

``python -m ecosystem.layout > docs/foxglove-layout.json`` writes the committed layout (a test
checks that it is this one). In Foxglove: Layouts, Import from file.

- a 3D panel in frame ``map``, following ``base_link``: the scene's mesh, the observed
  surface S_t (grey), the learned prediction (orange), the planner-facing map coloured by
  its ``source`` field (0 observed, 1 predicted, 2 oracle false negative, 3 truth; turbo
  colours from blue to red), the planned path and the camera's pose;
- the depth image (turbo colours, near to far);
- coverage against the step (``/rover/mission/status``'s ``coverage``);
- the mission status as it comes (step, state, condition, collisions).
"""

from __future__ import annotations

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
            topic("path"): fl.BaseRendererPosesTopicSettings(visible=True, type="line",
                                                               line_width=0.08),
            topic("pose"): fl.BaseRendererPoseTopicSettings(visible=True, type="arrow"),
        }))
    depth = fl.ImagePanel(title="depth", config=fl.ImageConfig(
        image_mode=fl.ImageModeConfig(image_topic=topic("depth"), color_mode="colormap",
                                      color_map="turbo")))
    coverage = fl.PlotPanel(title="coverage", config=fl.PlotConfig(paths=[
        fl.PlotSeries(value=f"{topic('status')}.coverage", label="coverage",
                      timestamp_method="headerStamp")]))
    status = fl.RawMessagesPanel(title="mission status", config=fl.RawMessagesConfig(
        topic_path=topic("status")))
    right = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(proportion=2, content=depth), fl.SplitItem(content=coverage),
        fl.SplitItem(content=status)])
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=2, content=three_d), fl.SplitItem(content=right)]))


def layout_json(namespace: str = "rover") -> str:
    import json
    return json.dumps(json.loads(layout(namespace).to_json()), indent=2) + "\n"


if __name__ == "__main__":
    print(layout_json(), end="")
