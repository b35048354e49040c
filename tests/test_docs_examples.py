"""Docs that cannot rot: every ```console example of README.md and docs/*.md is run, and what it
prints is compared with what the page shows.

Convention (also in docs/contributing.md):

* In a ```console block a line starting with ``$ `` is a command; the lines after it, up to the
  next ``$ `` line or the end of the block, are what it prints (stdout and stderr together, as a
  terminal shows them). A command line ending in ``\\`` continues on the next line.
* Each block runs as one bash session (variables and ``cd`` persist inside a block, as in one
  terminal). All blocks of one page run in page order in one scratch directory that holds
  ``scenes``, ``eds``, ``bench`` and ``docs`` (links to the repository's) and ``.venv`` (the
  environment running the tests); files a block writes are there for the next block. The
  environment's bin directory is first on PATH, so ``fusion-center`` works with or without
  activation. ``COLUMNS=120`` and ``NO_COLOR=1`` are set, so rich tables come out as on a page.
* Set-up lines are not run and print nothing here: ``python3 -m venv ...``, ``... pip install
  ...`` and ``. .venv/bin/activate`` / ``source .venv/bin/activate`` (CI runs the set-up:
  ``.ci/run``). Blocks that should not run at all are written as ```sh, not ```console.
* A command ending in `` &`` starts in the background (a second terminal): its output goes to a
  file, the session waits (at most 60 s) until it has printed as many lines as the page shows
  for it, and it is stopped (SIGTERM, then SIGKILL) when the block ends. In a command that uses
  ``udp_multicast``, ``port=NNNNN`` is replaced by one random port per block, so that two test
  runs on one machine do not share a bus; nothing else of a command is changed.
* Comparison (``compare``):
  - JSON: when the whole expected output, or an expected line, is JSON, the actual output (line)
    is parsed too and compared by keys and values: the same keys (an expected ``"...": "..."``
    entry allows more keys, a final ``"..."`` element of a list allows more elements), numbers
    with a relative tolerance of 1e-6, strings exactly (``...`` inside a string is a wildcard).
    Keys in ``VOLATILE_JSON_KEYS`` (times of the clock) are only required to exist.
  - text: every line is normalised (rich's box-drawing characters become spaces, runs of
    whitespace one space, blank and pure-border lines dropped), then lines are compared one by
    one: an expected line ``...`` matches any number of lines (also none), ``...`` inside a line
    matches any text within that line. Before comparing, ``VOLATILE_TEXT`` rewrites the values
    that depend on the machine's timing, not on the code, in both texts: the summary lines of a
    run that count late or degraded cycles, frames and latencies (``TIMING_SUMMARY_KEYS``, compared
    by name only), the elapsed time of a progress bar, and the ``nmt_restarts`` line a run prints only
    when nodes were found stopped on a slow host (removed).
"""

from __future__ import annotations

import difflib
import json
import math
import os
import random
import re
import shutil
import signal
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md"] + sorted((ROOT / "docs").glob("*.md"))
LINKED_DIRS = ("scenes", "eds", "bench", "docs")
BLOCK_TIMEOUT_S = 240
BACKGROUND_WAIT_S = 60

# Values that are clock times, not results: only their presence is checked.
VOLATILE_JSON_KEYS = frozenset({
    "t",                      # decision-log record: SYNC time since the first event (s)
})

# (pattern, replacement) applied to expected and actual text alike: values set by the machine's
# timing, not by the code's arithmetic. A run on the bus (demo, run, and the replay of their
# traces) is real time: on a loaded machine a node's TPDO can miss its SYNC period, so the cycle
# closes at the next SYNC without it (degraded, possibly undecided or wrong, the frame counted
# late) - the project's own tests allow for that (tests/test_service_e2e.py) - and how many
# heartbeats, boot-ups and echoes a run sees depends on how long boot and shut-down took. Those
# summary lines are compared by name only; everything else of a run exactly (scene, mode,
# cycles, records, nodes missing at boot, stages, skip reasons, SDO writes/aborts/timeouts).
TIMING_SUMMARY_KEYS = ("decisions", "agree_with_truth", "rules_agree_with_truth", "degraded_cycles",
                       "sync_overruns", "latency_ms", "counters", "own_echoes_dropped")
VOLATILE_TEXT = [
    (re.compile(r"^(\s*(?:" + "|".join(TIMING_SUMMARY_KEYS) + r"):)[^\n]*$", re.MULTILINE), r"\g<1> <timing>"),
    # elapsed time of a rich progress bar
    (re.compile(r"\b\d+:\d\d:\d\d\b"), "<h:mm:ss>"),
    # a summary line a run prints only when the host was slow: nodes that stopped on a late master
    # heartbeat (CiA 301 0x1029) and were started again by the master's supervision - removed
    (re.compile(r"^\s*nmt_restarts:[^\n]*\n?", re.MULTILINE), ""),
]

SETUP_LINE = re.compile(
    r"^\s*(?:python3? -m venv\b.*|.*\bpip3? install\b.*|(?:\.|source) \S*\.venv/bin/activate\s*)$")
BOX_CHARS = re.compile("[\u2500-\u257f]")
ELLIPSIS = "..."


# ---------------------------------------------------------------------------- parsing


@dataclass
class Command:
    text: str                 # the command as bash runs it (continuations joined)
    line: int                 # 1-based line of the page where it starts
    expected: list[str] = field(default_factory=list)
    background: bool = False
    setup: bool = False


@dataclass
class Block:
    page: Path
    line: int
    commands: list[Command]


def parse_console_blocks(text: str, page: Path = Path("<text>")) -> list[Block]:
    """Every ```console block of a markdown text, split into commands and their expected output."""
    blocks: list[Block] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        if lines[i].strip() == "```console":
            start = i + 1
            body: list[tuple[int, str]] = []
            i += 1
            while i < len(lines) and lines[i].strip() != "```":
                body.append((i + 1, lines[i]))
                i += 1
            blocks.append(Block(page, start, _commands(body)))
        i += 1
    return blocks


def _commands(body: list[tuple[int, str]]) -> list[Command]:
    commands: list[Command] = []
    k = 0
    while k < len(body):
        lineno, line = body[k]
        if line.startswith("$ "):
            text = line[2:]
            while text.endswith("\\") and k + 1 < len(body):
                k += 1
                text = text[:-1].rstrip() + " " + body[k][1].strip()
            cmd = Command(text=text.strip(), line=lineno)
            if cmd.text.endswith(" &"):
                cmd.background = True
                cmd.text = cmd.text[:-2].rstrip()
            cmd.setup = all(SETUP_LINE.match(part) for part in re.split(r"\s*&&\s*", cmd.text))
            commands.append(cmd)
        elif commands:
            commands[-1].expected.append(line)
        elif line.strip():
            raise ValueError(f"line {lineno}: output before the first '$ ' command: {line!r}")
        k += 1
    return commands


# ---------------------------------------------------------------------------- comparing


def _volatile(text: str) -> str:
    for pattern, repl in VOLATILE_TEXT:
        text = pattern.sub(repl, text)
    return text


def normalise_lines(text: str) -> list[str]:
    """Text as rows: box-drawing characters -> spaces, whitespace collapsed, empty lines dropped."""
    out = []
    for line in _volatile(text).splitlines():
        line = " ".join(BOX_CHARS.sub(" ", line).split())
        if line:
            out.append(line)
    return out


def _wildcard(pattern: str) -> re.Pattern:
    return re.compile(".*".join(re.escape(p) for p in pattern.split(ELLIPSIS)), re.DOTALL)


def _load_json(text: str):
    text = text.strip()
    if not text or text[0] not in "{[":
        return None, False
    try:
        return json.loads(text), True
    except ValueError:
        return None, False


def compare_json(expected, actual, path: str = "$") -> list[str]:
    """Differences between an expected and an actual JSON value (see the module docstring)."""
    if isinstance(expected, dict):
        if not isinstance(actual, dict):
            return [f"{path}: expected an object, got {actual!r}"]
        problems = []
        open_ended = expected.get(ELLIPSIS) == ELLIPSIS
        for key in expected:
            if key == ELLIPSIS and open_ended:
                continue
            if key not in actual:
                problems.append(f"{path}.{key}: missing")
            elif key not in VOLATILE_JSON_KEYS:
                problems += compare_json(expected[key], actual[key], f"{path}.{key}")
        if not open_ended:
            problems += [f"{path}.{key}: not on the page" for key in actual if key not in expected]
        return problems
    if isinstance(expected, list):
        if not isinstance(actual, list):
            return [f"{path}: expected a list, got {actual!r}"]
        open_ended = bool(expected) and expected[-1] == ELLIPSIS
        items = expected[:-1] if open_ended else expected
        if len(actual) < len(items) or (not open_ended and len(actual) != len(items)):
            return [f"{path}: {len(actual)} elements, the page shows {len(items)}"
                    + (" or more" if open_ended else "")]
        problems = []
        for n, (e, a) in enumerate(zip(items, actual)):
            problems += compare_json(e, a, f"{path}[{n}]")
        return problems
    if isinstance(expected, bool) or expected is None or isinstance(actual, bool):
        return [] if expected is actual or expected == actual and type(expected) is type(actual) \
            else [f"{path}: {actual!r} != {expected!r}"]
    if isinstance(expected, (int, float)):
        if not isinstance(actual, (int, float)):
            return [f"{path}: {actual!r} != {expected!r}"]
        if expected == actual or math.isclose(expected, actual, rel_tol=1e-6, abs_tol=0.0):
            return []
        return [f"{path}: {actual!r} != {expected!r}"]
    if isinstance(expected, str):
        if not isinstance(actual, str):
            return [f"{path}: {actual!r} != {expected!r}"]
        if ELLIPSIS in expected:
            return [] if _wildcard(expected).fullmatch(actual) else [f"{path}: {actual!r} !~ {expected!r}"]
        return [] if expected == actual else [f"{path}: {actual!r} != {expected!r}"]
    return [] if expected == actual else [f"{path}: {actual!r} != {expected!r}"]


def _line_matches(expected: str, actual: str) -> bool:
    if expected == actual:
        return True
    e, is_json = _load_json(expected)
    if is_json:
        a, ok = _load_json(actual)
        return ok and not compare_json(e, a)
    if ELLIPSIS in expected:
        return bool(_wildcard(expected).fullmatch(actual))
    return False


def _match_lines(expected: list[str], actual: list[str]) -> bool:
    """Line sequence match with '...' lines as 'any number of lines' (memoised backtracking)."""
    memo: dict[tuple[int, int], bool] = {}

    def go(i: int, j: int) -> bool:
        if (i, j) in memo:
            return memo[(i, j)]
        if i == len(expected):
            ok = j == len(actual)
        elif expected[i] == ELLIPSIS:
            ok = go(i + 1, j) or (j < len(actual) and go(i, j + 1))
        else:
            ok = j < len(actual) and _line_matches(expected[i], actual[j]) and go(i + 1, j + 1)
        memo[(i, j)] = ok
        return ok

    return go(0, 0)


def compare(expected: str, actual: str) -> list[str]:
    """Problems found comparing the page's text with the command's output; [] = they agree."""
    e_json, whole = _load_json(expected)
    if whole and "\n" in expected.strip():
        a_json, ok = _load_json(actual)
        if not ok:
            return ["the page shows JSON, the command printed something else"]
        return compare_json(e_json, a_json)
    exp, act = normalise_lines(expected), normalise_lines(actual)
    if _match_lines(exp, act):
        return []
    problems = []
    for e in exp:
        if e != ELLIPSIS and not any(_line_matches(e, a) for a in act):
            e_json, is_json = _load_json(e)
            detail = ""
            if is_json:
                # name the differing keys against the actual JSON line that differs least
                candidates = [compare_json(e_json, _load_json(a)[0]) for a in act if _load_json(a)[1]]
                if candidates:
                    detail = " (" + "; ".join(min(candidates, key=len)[:5]) + ")"
            problems.append(f"not printed: {e!r}{detail}")
    if ELLIPSIS not in exp:
        problems += [f"printed, not on the page: {a!r}" for a in act
                     if not any(_line_matches(e, a) for e in exp)]
    if not problems:
        problems.append("the lines differ in order or number")
    problems += ["diff (page -> printed, normalised):"] + list(
        difflib.unified_diff(exp, act, "page", "printed", lineterm="", n=1))
    return problems


# ---------------------------------------------------------------------------- running


def _scratch_dir(tmp: Path) -> Path:
    for name in LINKED_DIRS:
        (tmp / name).symlink_to(ROOT / name, target_is_directory=True)
    venv = ROOT / ".venv" if (ROOT / ".venv" / "bin").is_dir() else Path(sys.prefix)
    (tmp / ".venv").symlink_to(venv, target_is_directory=True)
    return tmp


def _marker(n: int) -> str:
    return f"\x1e{n}\x1e"


def _script(block: Block, workdir: Path) -> tuple[str, dict[int, Path]]:
    port = str(random.randint(20000, 39999))
    lines = ["exec 2>&1 </dev/null"]
    bg_files: dict[int, Path] = {}
    for n, cmd in enumerate(block.commands):
        lines.append(f"printf '\\n{_marker(n)}\\n'")
        if cmd.setup:
            continue
        text = cmd.text
        if "udp_multicast" in text:
            text = re.sub(r"\bport=\d+", f"port={port}", text)
        if cmd.background:
            out = workdir / f".bg-{block.line}-{n}.out"
            bg_files[n] = out
            want = sum(1 for e in cmd.expected if e.strip() and e.strip() != ELLIPSIS)
            lines += [
                f"( {text} ) > '{out}' 2>&1 &",
                f"__end=$((SECONDS + {BACKGROUND_WAIT_S}))",
                f"while [ \"$(grep -c . '{out}')\" -lt {want} ] && [ $SECONDS -lt $__end ] "
                f"&& kill -0 $! 2>/dev/null; do sleep 0.05; done",
                f"cp '{out}' '{out}.seen'",
            ]
        else:
            lines.append(text)
    lines.append(f"printf '\\n{_marker(len(block.commands))}\\n'")
    lines.append("__jobs=$(jobs -p); if [ -n \"$__jobs\" ]; then kill -TERM $__jobs 2>/dev/null; "
                 "for __k in $(seq 100); do kill -0 $__jobs 2>/dev/null || break; sleep 0.05; done; "
                 "kill -KILL $__jobs 2>/dev/null; fi; wait 2>/dev/null; true")
    return "\n".join(lines) + "\n", bg_files


def run_block(block: Block, workdir: Path) -> list[str]:
    """Run one block; its commands' outputs (background ones: what they printed while waited for)."""
    script, bg_files = _script(block, workdir)
    env = dict(os.environ)
    bindir = str(Path(sys.executable).parent)
    env.update(PATH=bindir + os.pathsep + env.get("PATH", ""), COLUMNS="120", LINES="50",
               NO_COLOR="1", TERM="dumb", VIRTUAL_ENV=str(workdir / ".venv"))
    env.pop("PYTHONSTARTUP", None)
    proc = subprocess.Popen(["bash", "--noprofile", "--norc", "-c", script], cwd=workdir, env=env,
                            stdout=subprocess.PIPE, stdin=subprocess.DEVNULL, start_new_session=True)
    try:
        raw, _ = proc.communicate(timeout=BLOCK_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        raw, _ = proc.communicate()
        raise AssertionError(f"{block.page.name}:{block.line}: block still running after "
                             f"{BLOCK_TIMEOUT_S} s; output so far:\n{raw.decode(errors='replace')[-3000:]}")
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)   # anything a background job left behind
        except ProcessLookupError:
            pass
    text = raw.decode(errors="replace")
    outputs = []
    for n in range(len(block.commands)):
        head, sep, rest = text.partition(_marker(n))
        if not sep:
            raise AssertionError(f"{block.page.name}:{block.line}: the block stopped before command {n + 1}")
        after = rest.partition(_marker(n + 1))[0]
        if n in bg_files:
            seen = Path(str(bg_files[n]) + ".seen")
            after = seen.read_text(errors="replace") if seen.exists() else ""
        outputs.append(after)
    return outputs


def check_page(page: Path, workdir: Path) -> list[str]:
    failures = []
    for block in parse_console_blocks(page.read_text(encoding="utf-8"), page):
        outputs = run_block(block, workdir)
        for cmd, out in zip(block.commands, outputs):
            if cmd.setup:
                continue
            problems = compare("\n".join(cmd.expected), out)
            if problems:
                failures.append(
                    f"{page.relative_to(ROOT)}:{cmd.line}: $ {cmd.text}\n  " + "\n  ".join(problems)
                    + "\n  --- printed:\n" + out.strip()[-3000:])
    return failures


def _pages_with_examples() -> list[Path]:
    return [p for p in PAGES if parse_console_blocks(p.read_text(encoding="utf-8"), p)]


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
@pytest.mark.parametrize("page", _pages_with_examples(), ids=lambda p: str(p.relative_to(ROOT)))
def test_console_examples_print_what_the_page_shows(page, tmp_path):
    failures = check_page(page, _scratch_dir(tmp_path))
    assert not failures, "\n\n".join(failures)


LINK = re.compile(r"\]\(([^)\s]+)\)|<img[^>]*\bsrc=\"([^\"]+)\"")


def _anchors(page: Path) -> set[str]:
    """GitHub's anchors of a page's headings."""
    out, fenced = set(), False
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif line.startswith("#") and not fenced:
            title = line.lstrip("#").strip().lower()
            out.add(re.sub(r"[^\w\- ]", "", title).replace(" ", "-"))
    return out


def test_links_between_pages_resolve():
    """Every relative link and image of README.md and docs/*.md names a file (and heading) that exists."""
    broken = []
    for page in PAGES:
        for match in LINK.finditer(page.read_text(encoding="utf-8")):
            target = match.group(1) or match.group(2)
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue
            path, _, anchor = target.partition("#")
            file = (page.parent / path).resolve()
            if not file.exists():
                broken.append(f"{page.name}: {target}")
            elif anchor and file.suffix == ".md" and anchor not in _anchors(file):
                broken.append(f"{page.name}: {target} (no such heading)")
    assert not broken, broken


# ---------------------------------------------------------------------------- the checker itself


def test_the_readme_tour_is_checked():
    """The README's examples are console blocks (so they run), and the set-up lines come first."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    commands = [c for b in parse_console_blocks(readme) for c in b.commands if not c.setup]
    for wanted in ("fusion-center demo", "node-sim", "fusion-center run", "fusion-center replay",
                   "fusion-center threshold", "fusion-center bandwidth", "fusion-center report"):
        assert any(c.text.startswith(wanted) for c in commands), f"the README tour has no `{wanted}` example"
    assert any(c.background for b in parse_console_blocks(readme) for c in b.commands)
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8").strip().splitlines()[-1]
    assert ci in readme.splitlines()[:8], "the README's test command must be the one .ci/run runs"


def test_parser_splits_commands_outputs_background_and_setup():
    page = "\n".join([
        "text", "```console", "$ . .venv/bin/activate", "$ node-sim --scene s.toml \\",
        "    --interface udp_multicast &", "ready", "$ echo hi", "hi", "", "```",
        "```sh", "$ not run", "```"])
    (block,) = parse_console_blocks(page)
    assert [c.text for c in block.commands] == [
        ". .venv/bin/activate", "node-sim --scene s.toml --interface udp_multicast", "echo hi"]
    assert [c.setup for c in block.commands] == [True, False, False]
    assert [c.background for c in block.commands] == [False, True, False]
    assert block.commands[1].expected == ["ready"]
    assert SETUP_LINE.match("python3 -m venv .venv")
    assert all(SETUP_LINE.match(p) for p in re.split(r"\s*&&\s*", "python3 -m venv .venv && .venv/bin/pip install -q -e ."))


TABLE = """\
┏━━━━━━━━━━━━━━━━┳━━━━━━━━━━━━┳━━━━━━━━━━┓
┃ mode           ┃ bits/cycle ┃ bus load ┃
┡━━━━━━━━━━━━━━━━╇━━━━━━━━━━━━╇━━━━━━━━━━┩
│ raw            │     5040.4 │  100.8 % │
│ decision_sync  │     3683.9 │   73.7 % │
└────────────────┴────────────┴──────────┘"""


def test_comparer_accepts_the_same_output_however_spaced():
    wide = TABLE.replace("│ raw            │", "│ raw │")
    assert compare(TABLE, wide) == []
    assert compare("scene:   matrix57\n...\nsdo: 945 writes", "scene: matrix57\na\nb\nsdo:  945 writes") == []
    assert compare("latency_ms: SYNC -> record p50 1.40 ms, p99 6.25 ms",
                   "latency_ms: SYNC -> record p50 2.27 ms, p99 9.01 ms") == []
    assert compare("counters: sync 50, tpdo1 2850, heartbeat 320, nmt 2",
                   "counters: sync 50, tpdo1 2793, late 57, heartbeat 334, nmt 2") == []
    assert compare("done ━━━━ 0:00:02\nwrote report.json", "done ━━━━ 0:00:07\nwrote report.json") == []
    assert compare("degraded_cycles:   0", "degraded_cycles: 2") == []
    assert compare('{"a": 1, "b": [1.0, 2.5], "t": 0.5}', '{"b": [1.0000000001, 2.5], "a": 1, "t": 7.25}') == []
    assert compare('{"a": 1, "...": "..."}', '{"a": 1, "b": 2}') == []
    assert compare('{"a": [1, "..."]}', '{"a": [1, 2, 3]}') == []
    assert compare('{\n  "a": 1,\n  "b": "x"\n}', '{"a": 1, "b": "x"}') == []
    assert compare("cycles: ... SYNC, 50 records", "cycles: 50 SYNC, 50 records") == []


def test_comparer_detects_a_changed_value_a_missing_row_and_a_changed_key():
    changed_cell = TABLE.replace("3683.9", "3683.8")
    assert compare(TABLE, changed_cell)
    missing_row = "\n".join(line for line in TABLE.splitlines() if "decision_sync" not in line)
    problems = compare(TABLE, missing_row)
    assert problems and "not printed: 'decision_sync 3683.9 73.7 %'" in problems[0]
    extra_row = TABLE.replace("└", "│ decision_event │      408.2 │    8.2 % │\n└")
    assert "printed, not on the page: 'decision_event 408.2 8.2 %'" in compare(TABLE, extra_row)
    assert compare("cycles: 50 SYNC, 50 records", "cycles: 50 SYNC, 49 records")
    assert compare("sdo: 945 writes, 0 aborts", "sdo: 945 writes, 1 aborts")
    assert compare("degraded_cycles: 0\nmissing_at_boot: none", "degraded_cycles: 0\nmissing_at_boot: 18")
    # JSON: a value, a missing key, an extra key, a float beyond the tolerance, a type change
    base = '{"rule": "additive", "thresholds": [-50.92886699707815], "present_counts": [4]}'
    assert compare(base, base) == []
    assert "($.present_counts[0]: 5 != 4)" in compare(base, base.replace("[4]", "[5]"))[0]
    assert compare(base, '{"rule": "additive", "thresholds": [-50.92886699707815]}') \
        and "missing" in compare(base, '{"rule": "additive", "thresholds": [-50.92886699707815]}')[0]
    assert compare(base, base[:-1] + ', "extra": 1}')
    assert compare(base, base.replace("-50.92886699707815", "-50.93"))
    assert compare('{"decision": "H1"}', '{"decision": null}')
    assert compare('{"n": 1}', '{"n": true}')
    assert compare('{"a": [1, 2]}', '{"a": [1, 2, 3]}')
    # a volatile key must still be there
    assert compare('{"t": 0.1, "cycle": 0}', '{"cycle": 0}')
    # a pretty-printed JSON page against other output
    assert compare('{\n  "a": 1\n}', "a = 1")
