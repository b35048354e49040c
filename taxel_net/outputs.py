"""Output paths a command writes whole or not at all, without harming what is not a file.

A command's output (``replay --json-lines``, ``plot --out``) goes to ``OUT.partial`` and is
renamed onto ``OUT`` when complete, so a failed command leaves nothing that looks complete -
for a regular file. A path that is not one - a character device (``/dev/null``), a FIFO a user
reads from, a socket, ``/dev/stdout`` (a symlink to one of those) - is written **in place**:
never renamed over, never deleted, on success or failure (issue 21: ``--json-lines /dev/null``
as root turned ``/dev/null`` into a regular file for every process on the machine, and a
failed replay deleted it). A symbolic link to a regular file stays a link: its target is the
output (written beside the target and renamed onto it).

:class:`OutputPath` says which it is; :func:`discard_stale` removes an earlier output the
failed command was to replace, only where that is a regular file.
"""

from __future__ import annotations

import logging
import os
import stat
from pathlib import Path

from .errors import UsageError

PARTIAL = ".partial"

log = logging.getLogger(__name__)


def _mode(path: Path) -> int | None:
    """``st_mode`` of what ``path`` names, following symbolic links; None if nothing is there."""
    try:
        return os.stat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return None


class OutputPath:
    """Where an output named ``path`` is written.

    ``in_place``: True when ``path`` names something that is not a regular file (a device,
    FIFO, socket, or a link to one): write it directly, no partial file, no rename, no delete.
    Otherwise ``target`` is the regular file to produce (``path`` itself, or the file a link
    points to), ``partial`` the file written first (``partial_name`` chooses its name, by
    default ``TARGET.partial``), and :meth:`commit` renames it onto the target. A directory is
    refused (:class:`UsageError` naming ``option``).
    """

    def __init__(self, path, partial_name=None, *, option: str = "output"):
        self.path = Path(path)
        mode = _mode(self.path)
        if mode is not None and stat.S_ISDIR(mode):
            raise UsageError(f"{option} {str(path)!r}: is a directory (give a file name)")
        self.in_place = mode is not None and not stat.S_ISREG(mode)
        self.target = self.path if self.in_place else Path(os.path.realpath(self.path))
        if self.in_place:
            self.partial = self.path
        elif partial_name is not None:
            self.partial = self.target.with_name(partial_name(self.target))
        else:
            self.partial = self.target.with_name(self.target.name + PARTIAL)

    @property
    def write_path(self) -> Path:
        """The path to open for writing: the partial file, or the special file itself."""
        return self.partial

    def commit(self) -> None:
        """The output is complete: rename the partial file onto the target (nothing to do in place)."""
        if not self.in_place:
            os.replace(self.partial, self.target)

    def discard_partial(self) -> None:
        """Remove the partial file written so far (never a special file); a file that cannot be
        removed is left, with a warning (this runs on a command's failure path: never raises)."""
        if not self.in_place and _is_regular(self.partial):
            _remove(self.partial, "the partial output")

    def discard_stale(self) -> None:
        """A failed run: remove an earlier output at the target so it cannot pass for this
        run's - only a regular file (see :func:`discard_stale`)."""
        discard_stale(self.path)


def _is_regular(path: Path) -> bool:
    try:
        return stat.S_ISREG(os.lstat(path).st_mode)
    except (FileNotFoundError, NotADirectoryError):
        return False


def discard_stale(path) -> bool:
    """Remove the regular file an output path names (the target of a link to one, the link kept),
    so an earlier run's output cannot pass for a failed run's; a device, FIFO, socket or
    directory is left alone. Returns whether a file was removed: a file that cannot be removed
    (``/proc/version``, a read-only file system) is left with a warning - this runs on a command's
    failure path, whose own error is the one to report, so it never raises."""
    p = Path(path)
    mode = _mode(p)
    if mode is None or not stat.S_ISREG(mode):
        return False
    if _input_marks(str(p)) & _INPUTS:  # the command's own input, never a stale output (stop 32)
        log.warning("%r is an input of this command: not removed", str(path))
        return False
    return _remove(Path(os.path.realpath(p)), "an earlier file at")


def _remove(path: Path, what: str) -> bool:
    try:
        path.unlink()
    except FileNotFoundError:
        return False
    except OSError as exc:
        log.warning("%s %r could not be removed (%s: %s): it is not this run's output", what, str(path),
                    type(exc).__name__, exc.strerror or exc)
        return False
    return True


# -- inputs and outputs that name one file (stop 32) ---------------------------------------------

_INPUTS: set = set()  # marks (_input_marks) of the running command's inputs (check_distinct_paths)

SAME_FILE_ALLOWED = ("each output needs a path of its own, neither an input's nor another output's "
                     "(only a character device or FIFO such as /dev/null may be named twice)")


def _identity(path: str):
    """What ``path`` names, for comparing paths: None for a character device, FIFO or socket
    (may be named twice: ``/dev/null``), ``("file", dev, inode)`` for something that exists
    (``os.path.samefile``'s test: a hard link or a symbolic link is the same file), else
    ``("path", realpath)`` (a file not yet written: two spellings of one path are one file)."""
    try:
        st = os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        return ("path", os.path.realpath(path))
    except OSError:  # a loop of links, a path too long...: compare what it spells
        return ("path", os.path.realpath(path))
    if stat.S_ISCHR(st.st_mode) or stat.S_ISFIFO(st.st_mode) or stat.S_ISSOCK(st.st_mode):
        return None
    return ("file", st.st_dev, st.st_ino)


def _input_marks(path: str) -> set:
    """How :func:`discard_stale` knows an input again: its resolved path and, when it exists, its
    (device, inode, ctime) - a hard link is the same file, a new file on a reused inode is not."""
    marks: set = {("path", os.path.realpath(path))}
    try:
        st = os.stat(path)
    except OSError:
        return marks
    marks.add(("file", st.st_dev, st.st_ino, st.st_ctime_ns))
    return marks


def _partials(path: str) -> list[str]:
    """The partial files an output at ``path`` is written as before its rename (``OUT.partial``,
    ``plot``'s ``OUT.partial.png``, a bag's ``DIR.partial``): an input there would be truncated."""
    real = Path(os.path.realpath(path))
    return [str(real.with_name(real.name + PARTIAL)),
            str(real.with_name(real.stem + PARTIAL + real.suffix))]


def check_distinct_paths(inputs, outputs) -> None:
    """Refuse, before anything is opened for writing, an output that names an input or another
    output (``replay --scene S c.log --json-lines c.log`` truncated its own trace; ``demo
    --json-lines x.log --log x.log`` wrote both into one file; a failed replay then deleted the
    trace as a stale output). ``inputs`` and ``outputs`` are ``(option, path)`` pairs (a path of
    None or ``-``, stdout, is skipped); paths are compared resolved (``os.path.realpath``) and,
    where both exist, as ``os.path.samefile`` does. A character device, FIFO or socket may be
    named any number of times (``--json-lines /dev/null --mcap /dev/null``). An input that is an
    output's partial file (``OUT.partial``) is refused too. Raises :class:`UsageError` in one
    line naming both options and the path."""
    # (option, path, is_output) of every path named, inputs first; None and "-" (stdout) skipped
    named = [(option, str(path), is_output) for is_output, pairs in ((False, inputs), (True, outputs))
             for option, path in pairs if path is not None and str(path) != "-"]
    _INPUTS.clear()  # this command's inputs: discard_stale never removes one of them
    for _, path, is_output in named:
        if not is_output:
            _INPUTS.update(_input_marks(path))
    seen: dict = {}  # identity -> (option, path, is_output)
    for option, path, is_output in named:
        key = _identity(path)
        if key is None:
            continue
        if key in seen and is_output:  # an input read twice (two options) harms nothing
            first_option, first_path, first_is_output = seen[key]
            what = "another output" if first_is_output else "an input"
            raise UsageError(f"{option} {path!r}: is {what}, {first_option} {first_path!r}; "
                             f"{SAME_FILE_ALLOWED}")
        seen.setdefault(key, (option, path, is_output))
    for out_option, out_path, is_output in named:
        if not is_output or _identity(out_path) is None:
            continue
        partials = set(_partials(out_path))
        for option, path, other_is_output in named:
            if path != out_path and os.path.realpath(path) in partials and _identity(path) is not None:
                what = "another output" if other_is_output else "an input"
                raise UsageError(f"{out_option} {out_path!r}: is written first as {path!r}, which is {what}, "
                                 f"{option} {path!r}; {SAME_FILE_ALLOWED}")


def scene_inputs(text, option: str = "--scene") -> list[tuple[str, str]]:
    """The files a scene argument reads, as ``(option, path)`` pairs for
    :func:`check_distinct_paths`: the scene file (a bundled name resolved to its file) and its
    ``taxels_file`` CSV, if any. A scene that cannot be resolved or read gives its text alone
    (the loader reports it)."""
    from .resources import resolve_scene

    try:
        path = resolve_scene(text)
    except Exception:  # noqa: BLE001 - the loader's error is the one to report
        return [(option, str(text))]
    found = [(option, str(path))]
    try:
        import tomllib

        with open(path, "rb") as fh:
            rel = tomllib.load(fh).get("taxels_file")
    except Exception:  # noqa: BLE001 - unreadable or not TOML: the loader says so
        return found
    if isinstance(rel, str) and rel:
        found.append((f"{option}'s taxels_file", str(Path(path).parent / rel)))
    return found
