"""The Foxglove layouts in ``docs/foxglove/`` (docs/robotics.md), built with the SDK's own layout
types (``foxglove.layouts``: ``Layout.to_json``, the layout JSON Foxglove imports):

* ``taxel-can.json``: the sensor's taxel map (``/taxel/sensor/map``), the decision plot (U_G of
  the deciding rule against its threshold, the decision and the truth as numbers, P(H1)), the
  contact plot (area, t_c) and the bus plot (SYNC -> close, late and malformed frames);
* ``taxel-can-gripper.json``: the two jaws' maps (``/taxel/left/map``, ``/taxel/right/map``), the
  decision plot and the grip plot (commanded and actual grip force, the world's normal force and
  minimum hold force, slip).

``python -m fusion_center.robotics.layouts docs/foxglove`` writes them; ``tests/test_robotics_layouts.py``
checks the files are what this module builds.
"""

from __future__ import annotations

import sys
from pathlib import Path

from .topics import T_BUS, T_CONTACT, T_DECISION, T_GRIP, T_TRUTH

FILES = {"taxel-can.json": ("sensor",), "taxel-can-gripper.json": ("left", "right")}


def _plot(title: str, series: list[tuple[str, str]]):
    import foxglove.layouts as fl

    return fl.PlotPanel(title=title, config=fl.PlotConfig(
        paths=[fl.PlotSeries(value=value, label=label, timestamp_method="receiveTime") for value, label in series],
        show_legend=True, legend_display="top", is_synced=True))


def _map(pad: str):
    import foxglove.layouts as fl

    return fl.ImagePanel(title=f"taxel map: {pad}", config=fl.ImageConfig(
        image_mode=fl.ImageModeConfig(image_topic=f"/taxel/{pad}/map")))


def decision_plot():
    return _plot("decision", [(f"{T_DECISION}.U_G", "U_G"), (f"{T_DECISION}.threshold", "threshold"),
                              (f"{T_DECISION}.decision_code", "decision (H1 1, H0 0, undecided -1)"),
                              (f"{T_DECISION}.truth_code", "truth (H1 1, H0 0)"), (f"{T_DECISION}.p_h1", "P(H1)")])


def grip_plot():
    return _plot("grip", [(f"{T_GRIP}.command_n", "command (N)"), (f"{T_GRIP}.actual_n", "actual (N)"),
                          (f"{T_TRUTH}.normal_n", "world: normal force (N)"),
                          (f"{T_TRUTH}.min_hold_n", "world: minimum hold force (N)"),
                          (f"{T_TRUTH}.slid_mm", "world: slid (mm)")])


def build(pads: tuple[str, ...]):
    """The layout for a scene with these pads (a gripper's jaws get the grip plot)."""
    import foxglove.layouts as fl

    maps = fl.SplitContainer(direction="column", items=[fl.SplitItem(content=_map(p)) for p in pads]) \
        if len(pads) > 1 else _map(pads[0])
    if set(pads) >= {"left", "right"}:
        plots = [decision_plot(), grip_plot()]
    else:
        plots = [decision_plot(),
                 _plot("contact", [(f"{T_CONTACT}.area", "area (mm^2)"), (f"{T_CONTACT}.t_c", "t_c")]),
                 _plot("bus", [(f"{T_BUS}.closed_after_ms", "SYNC -> close (ms)"),
                               (f"{T_BUS}.late_frames", "late frames"), (f"{T_BUS}.bad_frames", "malformed frames"),
                               (f"{T_BUS}.not_taking_part", "nodes not taking part")])]
    right = fl.SplitContainer(direction="column", items=[fl.SplitItem(content=p) for p in plots])
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=1, content=maps), fl.SplitItem(proportion=2, content=right)]))


def render(name: str) -> str:
    """The JSON text of ``docs/foxglove/<name>`` (indented, one trailing newline)."""
    import json

    return json.dumps(json.loads(build(FILES[name]).to_json()), indent=2) + "\n"


def main(argv: list[str] | None = None) -> int:
    out = Path((argv or sys.argv[1:] or ["docs/foxglove"])[0])
    out.mkdir(parents=True, exist_ok=True)
    for name in FILES:
        (out / name).write_text(render(name))
        print(f"wrote {out / name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
