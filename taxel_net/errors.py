"""Errors shared by the numerical core, the scene loader, the service and the CLIs.

Each is a bad input the user can fix: the CLIs print it as one line and exit 2."""

from __future__ import annotations


class ParameterError(ValueError):
    """A parameter outside its allowed domain.

    The message always names the parameter, the value received and what is allowed, e.g.
    ``xi=1.5: must lie in the open interval (0, 1)``. The CLI prints it as one line on
    stderr and exits 2.
    """

    def __init__(self, name: str, value: object, allowed: str):
        self.name = name
        self.value = value
        self.allowed = allowed
        super().__init__(f"{name}={value!r}: {allowed}")


class SceneError(ValueError):
    """A scene file that cannot be used: names the file, the field and the value."""

    def __init__(self, path: str, field: str, value: object, problem: str):
        self.path = path
        self.field = field
        self.value = value
        self.problem = problem
        super().__init__(f"{path}: {field}={value!r}: {problem}")


class EdsError(ParameterError):
    """An EDS file (CiA 306) that cannot be used: the message names the file, then the line or the
    section, key and value, or the object that is missing (``taxel_net.eds_file``). A
    :class:`ParameterError` (parameter ``eds``): the CLIs print it as one line and exit 2."""

    def __init__(self, path, problem: str):
        self.path = str(path)
        self.problem = problem
        self.name, self.value, self.allowed = "eds", self.path, problem
        ValueError.__init__(self, f"EDS file {self.path!r}: {problem}")


class UsageError(Exception):
    """A bad input at the command or service level (unknown interface, unreadable file...): exit 2."""


def one_line(exc: BaseException) -> str:
    """An exception as one line, ``Type: message`` with its whitespace collapsed (for the one-line
    errors of bad files and traces)."""
    return " ".join(f"{type(exc).__name__}: {exc}".split())
