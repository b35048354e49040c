"""Write the taxel tables of the skin-scale scenes (issue 14): scenes/data/skin4096_*.csv.

A 64 x 64 grid of capacitive taxels at 5 mm pitch (x, y = 2.5 .. 317.5 mm), fusion order
row-major. Eight CAN channels, each a strip of 8 rows (512 taxels):

* ``skin4096_taxels.csv`` (patch nodes): on each channel node 1 hosts rows 0-2 of the strip
  (192 taxels, the size of a humanoid-skin patch microcontroller), node 2 rows 3-5 (192),
  node 3 rows 6-7 (128); 24 patch nodes in all.
* ``skin4096_per_taxel_taxels.csv`` (the chapter's one-taxel nodes): 4,096 nodes need 33
  CANopen networks of at most 127 nodes: 125 taxels per channel, node-IDs 1..125 (the last
  channel holds 96; 127 stays free for the master's heartbeat).

Run: python bench/make_skin_scene.py
"""

from __future__ import annotations

import csv
from pathlib import Path

DATA = Path(__file__).resolve().parent.parent / "scenes" / "data"
SIDE, PITCH = 64, 5.0
ROWS_PER_CHANNEL = 8
PATCH_ROWS = (3, 3, 2)          # rows per patch node within a strip: 192, 192, 128 taxels
PER_TAXEL_CHANNEL = 125


def grid():
    for r in range(SIDE):
        for c in range(SIDE):
            yield r, c, PITCH * c + PITCH / 2, PITCH * r + PITCH / 2


def patch_rows():
    starts = [sum(PATCH_ROWS[:k]) for k in range(len(PATCH_ROWS))]
    for index, (r, _c, x, y) in enumerate(grid()):
        strip_row = r % ROWS_PER_CHANNEL
        node = max(k for k, s in enumerate(starts) if strip_row >= s) + 1
        yield {"node_id": node, "kind": "C", "x": x, "y": y, "channel": r // ROWS_PER_CHANNEL}


def per_taxel_rows():
    for index, (_r, _c, x, y) in enumerate(grid()):
        yield {"node_id": index % PER_TAXEL_CHANNEL + 1, "kind": "C", "x": x, "y": y,
               "channel": index // PER_TAXEL_CHANNEL}


def write(name: str, rows) -> None:
    out = DATA / name
    with out.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=["node_id", "kind", "x", "y", "channel"])
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {out}")


def main() -> None:
    write("skin4096_taxels.csv", patch_rows())
    write("skin4096_per_taxel_taxels.csv", per_taxel_rows())


if __name__ == "__main__":
    main()
