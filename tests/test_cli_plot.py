"""``fusion-center plot RUN.jsonl -o OUT.png`` (issue 12): the figure shows what the decision
log holds (checked on the drawn data, not only that a file appeared), and a log or output
path it cannot use exits 2 with one line and leaves no file."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from fusion_center import cli
from fusion_center.commands import plot

ROOT = Path(__file__).resolve().parent.parent
CLI = [sys.executable, "-c", "import sys; from fusion_center.cli import main; sys.exit(main())"]


def records(n=30):
    """A decision log as the service writes it: an object on cycles 10-19, node 18 silent from
    cycle 20, node 27 missing from 25, late frames in cycle 1, one undecided and one wrong cycle."""
    out = []
    for k in range(n):
        truth = "H1" if 10 <= k < 20 else "H0"
        decision = truth
        if k == 0:
            decision = "undecided"
        if k == 15:
            decision = "H0"  # a miss
        by_state = {}
        if k >= 20:
            by_state["silent"] = [18]
        if k >= 25:
            by_state["missing"] = [27]
        out.append({
            "cycle": k, "t": round(0.2 + 0.01 * k + (0.002 if k == 5 else 0.0), 6), "closed_by": "complete" if k < 20
            else "window", "n_expected": 57, "mode": "decision", "decide_with": "additive",
            "U_G": None if decision == "undecided" else (-45 if truth == "H1" else -56) - (4 if k == 15 else 0),
            "threshold": -50.9 if k < 20 else -50.0, "decision": decision, "truth": truth,
            "missing_nodes": by_state.get("missing", []), "silent_nodes": by_state.get("silent", []),
            "nodes_by_state": by_state, "late_frames": 57 if k == 1 else 0, "bad_frames": 2 if k == 7 else 0,
        })
    return out


def write_log(path: Path, recs) -> Path:
    path.write_text("".join(json.dumps(r) + "\n" for r in recs))
    return path


def test_plot_draws_the_log(tmp_path, monkeypatch):
    """The panels carry the log's numbers: U_G and threshold per cycle, decision counts, the
    agreement with the truth, nodes by state, late frames, SYNC gaps."""
    import fusion_center.report.plots as report_plots

    figures = []
    real_save = report_plots._save

    def keep(fig, path):
        figures.append(fig)
        real_save(fig, path)
    monkeypatch.setattr(report_plots, "_save", keep)
    log = write_log(tmp_path / "run.jsonl", records())
    out = tmp_path / "run.png"
    assert cli.main(["plot", str(log), "-o", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and not list(tmp_path.glob("*.partial*"))
    fig = figures[0]
    top, nodes, frames, timing = fig.axes
    assert fig._suptitle.get_text() == "run.jsonl (decision mode): 30 cycles; agree with truth 28/29"
    lines = {line.get_label(): line for line in top.get_lines()}
    u_g = lines["U_G (additive)"].get_ydata()
    assert list(u_g[10:13]) == [-45, -45, -45] and u_g[15] == -49 and str(u_g[0]) == "nan"
    assert list(lines["threshold"].get_ydata()[[0, 25]]) == [-50.9, -50.0]
    assert len(lines["decision H1 (9)"].get_xdata()) == 9 and len(lines["decision H0 (20)"].get_xdata()) == 20
    assert list(lines["decision != truth (1, at the top)"].get_xdata()) == [15]
    assert list(lines["undecided (1, at the bottom)"].get_xdata()) == [0]
    legend = [t.get_text() for t in nodes.get_legend().get_texts()]
    assert legend == ["missing (in 5 cycles, at most 1)", "silent (in 10 cycles, at most 1)"]
    heights = [p.get_height() for p in frames.patches]
    assert heights[1] == 57 and heights[30 + 7] == 2 and sum(heights) == 59  # late, then malformed on top
    gaps = timing.get_lines()[0].get_ydata()
    assert gaps[4] == pytest.approx(12.0) and gaps[5] == pytest.approx(8.0) and gaps[0] == pytest.approx(10.0)


def test_plot_shows_the_decision_latency_and_takes_an_output_directory(tmp_path, monkeypatch):
    """``closed_after_ms`` (SYNC to the cycle's close) per cycle by ``closed_by``, and its
    histogram in an inset; ``--out DIR`` writes DIR/RUN.png."""
    import fusion_center.report.plots as report_plots

    figures = []
    real_save = report_plots._save
    monkeypatch.setattr(report_plots, "_save", lambda fig, path: (figures.append(fig), real_save(fig, path)))
    recs = records()
    for r in recs:
        r["closed_after_ms"] = 3.25 if r["closed_by"] == "complete" else 8.0
    log = write_log(tmp_path / "lat.jsonl", recs)
    outdir = tmp_path / "figs"
    outdir.mkdir()
    assert cli.main(["plot", str(log), "--out", str(outdir)]) == 0
    assert (outdir / "lat.png").read_bytes()[:4] == b"\x89PNG"
    fig = figures[0]
    timing = fig.axes[3]
    inset, = timing.child_axes
    lines = {line.get_label(): line for line in timing.get_lines()}
    assert list(lines["SYNC to close, complete (20)"].get_ydata()) == [3.25] * 20
    assert list(lines["SYNC to close, window (10)"].get_xdata()) == list(range(20, 30))
    assert sum(p.get_height() for p in inset.patches) == 30
    assert "p50 3.25" in inset.get_title() and "p99 8.00" in inset.get_title()


def test_plot_default_output_next_to_the_log(tmp_path, capsys):
    log = write_log(tmp_path / "r.jsonl", records(5))
    assert cli.main(["plot", str(log)]) == 0
    assert (tmp_path / "r.png").is_file()
    assert capsys.readouterr().out.strip() == f"wrote {tmp_path / 'r.png'} (5 cycles)"


def test_plot_cli_exit_code(tmp_path):
    log = write_log(tmp_path / "r.jsonl", records(12))
    done = subprocess.run(CLI + ["plot", str(log), "-o", str(tmp_path / "r.svg")], cwd=ROOT, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "r.svg").read_text().lstrip().startswith("<?xml")


@pytest.mark.parametrize("content, needle", [
    (None, "not found"),
    ("", "no records"),
    ('{"cycle": 0}\n{"cycle": 1}\n{"cycle": 2, "U_G":\n', "line 3: not a JSON record"),
    ('{"cycle": 0}\n[1, 2]\n', "line 2: not a decision record"),
    ('{"scene": "x"}\n', "line 1: not a decision record"),
    (b"\xff\xfe\x00garbage", "not a UTF-8 text file"),
    ('{"cycle": 0}\n' + "[" * 200_000 + "\n", "line 2: not a JSON record (nested too deeply)"),  # was a RecursionError
    # fields the figures read, of the wrong type (2026-11-30, stop 32: tracebacks, or an empty figure and exit 0)
    ('{"cycle": 0, "t": 0.0}\n{"cycle": 1, "t": 0.01, "nodes_by_state": [1]}\n', "line 2: nodes_by_state [1]"),
    ('{"cycle": 0, "t": 0.0, "missing_nodes": 3}\n', "line 1: missing_nodes 3: must be a list"),
    ('{"cycle": 0, "t": "0.0"}\n', "line 1: t '0.0': the record's SYNC time must be a finite number"),
    ('{"cycle": 0, "t": 0.0, "grip": {"command_n": 1}, "grasp_truth": {"phase": {"x": [1, 2]}}}\n',
     "line 1: grasp_truth.phase {'x': [1, 2]}: must be a phase name"),
    ('{"cycle": 0, "t": 0.0, "grip": [1]}\n', "line 1: grip [1]: must be an object"),
])
def test_bad_logs_exit_2_with_one_line(tmp_path, capsys, content, needle):
    log = tmp_path / "bad.jsonl"
    if isinstance(content, bytes):
        log.write_bytes(content)
    elif content is not None:
        log.write_text(content)
    out = tmp_path / "bad.png"
    assert cli.main(["plot", str(log), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0] and str(log) in err[0], err
    assert not out.exists() and not list(tmp_path.glob("*.partial*"))


@pytest.mark.parametrize("out, needle", [
    ("x.jpg2", "unknown figure format '.jpg2'"),
    ("no/such/dir/x.png", "does not exist"),
])
def test_bad_output_exits_2(tmp_path, capsys, out, needle):
    log = write_log(tmp_path / "r.jsonl", records(3))
    assert cli.main(["plot", str(log), "-o", str(tmp_path / out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]


def test_bad_log_exit_code_in_a_subprocess(tmp_path):
    log = tmp_path / "broken.jsonl"
    log.write_text('{"cycle": 0}\nnot json\n')
    done = subprocess.run(CLI + ["plot", str(log)], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.strip().count("\n") == 0 and "line 2" in done.stderr
    assert not (tmp_path / "broken.png").exists()


def test_thinned_markers_for_long_logs(tmp_path, monkeypatch):
    """A long log draws at most about MARKERS_MAX markers per kind; the legend counts every cycle."""
    import fusion_center.report.plots as report_plots

    figures = []
    monkeypatch.setattr(report_plots, "_save", lambda fig, path: figures.append(fig))
    monkeypatch.setattr(plot, "MARKERS_MAX", 10)
    series = plot.read_log(write_log(tmp_path / "r.jsonl", records(30)))
    plot.draw(series, "t", tmp_path / "r.png")
    lines = {line.get_label(): line for line in figures[0].axes[0].get_lines()}
    assert len(lines["decision H0 (20)"].get_xdata()) == 7  # every third of 20 (30 records // 10)
    assert len(lines["U_G (additive)"].get_xdata()) == 30   # the line keeps every cycle
