"""The pad layout of the grasp scenes (``scenes/grasp_lift*.toml``, ``scenes/grasp_fragile.toml``)
and of ``bench/grasp.py``'s randomised grasps: one function of the pad pitch.

Per pad (jaw-local mm: ``y`` up the 40 mm pad, the slip axis; ``x`` across it), identical on both
jaws (node-IDs 1.. on the left, then the right):

* a **row of pressure cells** (kind P) at ``x = 20`` along ``y``, at the pitch, symmetric about the
  pad's middle ``y = 20`` (the contact's centre at rest): as the object slides down the pads the
  row's cells leave the footprint at its top and enter at its bottom, so the present taxels'
  centroid moves with the slide (one taxel pitch of slide moves it by about one pitch x the row's
  share of the footprint's locations);
* one load cell (LC) at ``(20, 20)`` (the row's middle location: no location of its own), for raw
  mode's grip force (eq 27b);
* four thin-beam cells (TBS, axis y) at ``(8 | 32, 14 | 26)``, for raw mode's tangential load
  (eqs 27a, 28-30), symmetric about ``(20, 20)``: they switch on and off together with the load and
  do not move the centroid;
* two presence cells (IR) at ``(4 | 36, 20)``: they see the object from the close phase on, before
  the jaws touch it (the grasp starts on presence), symmetric about ``(20, 20)``.

Every distinct location is at least one pitch from every other (pitch <= 7 mm), so the slip
stage's noise band (half the smallest distance between locations) is half the pitch.

``patch=True`` (``scenes/data/grasp_pads_2mm_patch.csv``, the ``*_patch`` grasp scenes with
``[bus] patch_nodes = true``): the same taxels in the same order, each pad one patch node (node-ID
1 on the left jaw, 2 on the right) sending its 26 taxels' decisions or readings packed
(``taxel_net.patches``) instead of 26 one-taxel nodes.
"""

from __future__ import annotations

PAD_MM = 40.0
CENTRE = (20.0, 20.0)
TBS_XY = ((8.0, 14.0), (32.0, 14.0), (8.0, 26.0), (32.0, 26.0))
IR_XY = ((4.0, 20.0), (36.0, 20.0))


def row_ys(pitch_mm: float) -> list[float]:
    """The pressure row's heights: ``20 + k pitch`` within the pad (0 < y < 40), sorted."""
    if not 0.5 <= pitch_mm <= 12.0:
        raise ValueError(f"pitch_mm={pitch_mm!r}: must lie in 0.5..12 mm")
    k = int((CENTRE[1] - 1e-9) // pitch_mm)
    return [round(CENTRE[1] + i * pitch_mm, 6) for i in range(-k, k + 1)]


def pad_rows(pitch_mm: float, patch: bool = False) -> list[dict]:
    """The taxels of both pads as CSV-like rows (node_id, kind, x, y, jaw, axis); ``patch``: one
    node-ID per pad (module docstring)."""
    one = [("LC", *CENTRE, None)]
    one += [("TBS", x, y, "y") for x, y in TBS_XY]
    one += [("IR", x, y, None) for x, y in IR_XY]
    one += [("P", CENTRE[0], y, None) for y in row_ys(pitch_mm)]
    rows = []
    for jaw in ("left", "right"):
        for kind, x, y, axis in one:
            node_id = (1 if jaw == "left" else 2) if patch else len(rows) + 1
            rows.append({"node_id": node_id, "kind": kind, "x": x, "y": y, "jaw": jaw, "axis": axis})
    return rows


def write_csv(path, pitch_mm: float, patch: bool = False) -> None:
    cols = ("node_id", "kind", "x", "y", "jaw", "axis")
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(",".join(cols) + "\n")
        for r in pad_rows(pitch_mm, patch):
            f.write(",".join("" if r[c] is None else f"{r[c]:g}" if isinstance(r[c], float) else str(r[c])
                             for c in cols) + "\n")


if __name__ == "__main__":  # python bench/grasp_layout.py scenes/data/grasp_pads_2mm.csv 2.0 [patch]
    import sys

    write_csv(sys.argv[1], float(sys.argv[2]), patch=sys.argv[3:] == ["patch"])
