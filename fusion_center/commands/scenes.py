"""``fusion-center scenes``: the bundled scenes, by the name every ``--scene`` accepts."""

from __future__ import annotations

import argparse
import json

HELP = "list the bundled scenes (any --scene option takes their name, e.g. --scene matrix57)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print the list as JSON")


def scene_rows() -> list[dict]:
    """One row per bundled scene: name, taxels, channels, bus mode, cycles, description."""
    from taxel_net.resources import bundled_scenes
    from taxel_net.scene import load_scene

    rows = []
    for name, path in bundled_scenes().items():
        scene = load_scene(path)
        rows.append({"name": name, "taxels": scene.n, "channels": len(scene.bus.channels),
                     "mode": scene.bus.mode, "cycles": scene.cycles, "description": scene.description})
    return rows


def run(args) -> int:
    rows = scene_rows()
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    import shutil

    width = shutil.get_terminal_size((100, 24)).columns
    cols = ("name", "taxels", "channels", "mode", "cycles")
    widths = {c: max([len(c)] + [len(str(r[c])) for r in rows]) for c in cols}

    def line(values: dict) -> str:
        head = "  ".join(str(values[c]).ljust(widths[c]) if c in ("name", "mode") else str(values[c]).rjust(widths[c])
                         for c in cols)
        room = max(12, width - len(head) - 2)
        text = str(values["description"])
        return f"{head}  {text if len(text) <= room else text[:room - 3] + '...'}".rstrip()

    print(line({c: c for c in cols + ("description",)}))
    for r in rows:
        print(line(r))
    return 0
