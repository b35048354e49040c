"""docs/foxglove/*.json: the layouts the SDK's layout types build (the format Foxglove imports),
and every topic and field they plot is one the outputs write (issue 24)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from fusion_center.robotics import layouts
from fusion_center.robotics.topics import TopicMap
from taxel_net.scene import load_scene

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))


def _panels(node):
    if node.get("type") == "panel":
        yield node
    for item in node.get("items", []):
        yield from _panels(item["content"])


@pytest.mark.parametrize("name", sorted(layouts.FILES))
def test_the_checked_in_layout_is_the_built_one(name):
    text = (ROOT / "docs" / "foxglove" / name).read_text()
    assert text == layouts.render(name), "regenerate: python -m fusion_center.robotics.layouts docs/foxglove"
    layout = json.loads(text)
    assert layout["version"] == 1 and {p["panelType"] for p in _panels(layout["content"])} == {"Image", "Plot"}


@pytest.mark.parametrize("name, scene_name", [("taxel-can.json", "matrix57"),
                                              ("taxel-can-gripper.json", "grasp_drive")])
def test_every_plotted_field_and_image_topic_is_published(name, scene_name):
    from test_robotics_mcap import _grasp_record

    scene = load_scene(scene_name)
    topics = TopicMap(scene)
    if scene_name == "matrix57":
        from fusion_center.commands.demo import run_demo

        service, _ = run_demo(scene, 30, keep_records=True)
        # a cycle that saw the contact (its fields are published only then; on a loaded host a
        # given cycle may have closed without the answers that show it)
        record = max(service.records, key=lambda r: r["present_count"])
    else:
        record = _grasp_record(2)
    messages = dict(topics.values(record))
    images = {pad.map_topic for pad in topics.pads}
    layout = json.loads((ROOT / "docs" / "foxglove" / name).read_text())
    for panel in _panels(layout["content"]):
        if panel["panelType"] == "Image":
            assert panel["config"]["imageMode"]["imageTopic"] in images
        else:
            for series in panel["config"]["paths"]:
                topic, _, field = series["value"].partition(".")
                assert topic in messages, series["value"]
                assert field in messages[topic], series["value"]
