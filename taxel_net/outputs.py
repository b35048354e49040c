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
