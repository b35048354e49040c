"""Write scenes/data/two_buses_200_taxels.csv: 200 taxels on two CAN channels (> 127 nodes).

A 20 x 10 grid at 10 mm pitch (x = 5..195, y = 5..95), kinds alternating R / C along each row.
Rows 0-4 (taxels 1-100 in fusion order) sit on channel 0 with node-IDs 1..100, rows 5-9 on
channel 1 with node-IDs 1..100 again: one CANopen network per channel, node-IDs unique per
channel (CiA 301 allows 1..127 per network). Run: python bench/make_big_scene.py
"""

from __future__ import annotations

import csv
from pathlib import Path

OUT = Path(__file__).resolve().parent.parent / "scenes" / "data" / "two_buses_200_taxels.csv"
COLUMNS, ROWS, PITCH = 20, 10, 10.0


def rows():
    for r in range(ROWS):
        for c in range(COLUMNS):
            index = r * COLUMNS + c                    # fusion order
            channel = 0 if index < 100 else 1
            yield {
                "node_id": index % 100 + 1,
                "kind": "R" if c % 2 == 0 else "C",
                "x": PITCH * c + 5.0,
                "y": PITCH * r + 5.0,
                "channel": channel,
            }


def main() -> None:
    with OUT.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=["node_id", "kind", "x", "y", "channel"])
        writer.writeheader()
        writer.writerows(rows())
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
