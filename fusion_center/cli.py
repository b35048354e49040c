"""``fusion-center`` command line: one sub-command per module in ``fusion_center.commands``.

Each command module exposes ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``. Errors the user can fix (ParameterError, SceneError, UsageError)
exit 2 with one line on stderr, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from taxel_net.errors import ParameterError, SceneError, UsageError

# sub-command name -> module under fusion_center.commands (imported lazily: start-up stays fast)
COMMANDS: dict[str, str] = {
    "run": "run",
    "demo": "demo",
    "replay": "replay",
    "threshold": "threshold",
    "fuse": "fuse",
    "bandwidth": "bandwidth",
    "report": "report",
    "scenes": "scenes",
    "dcf": "dcf",
    "plot": "plot",
    "assemble": "assemble",
    "export": "export",
}


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own errors: one line, exit 2
        self.exit(2, f"{self.prog}: error: {message}\n")


def _load(name: str):
    return importlib.import_module(f"fusion_center.commands.{COMMANDS[name]}")


def package_version() -> str:
    """The installed distribution's version (``taxel-can``), as ``pip show`` reports it."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("taxel-can")
    except PackageNotFoundError:  # run from a checkout that was never installed
        from . import __version__

        return __version__


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The CLI's parser; with ``only`` (a sub-command name) only that command's module is
    imported and its options added - the others are listed by name, so a wrong name still gets
    argparse's "invalid choice" with every choice, and ``fusion-center threshold ...`` does not
    import the service, the report and their libraries (0.7 s of a 1 s start)."""
    parser = _Parser(prog="fusion-center", description="HEBTEM fusion centre for a CANopen taxel network")
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for name in COMMANDS:
        if only is not None and name != only:
            sub.add_parser(name)
            continue
        try:
            module = _load(name)
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.startswith("fusion_center.commands."):
                continue  # command not built yet
            raise
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """``fusion-center ARGS`` (``argv``; None: the program's own, ``sys.argv[1:]``): the exit
    status. Run as the program (``argv`` None) by a command that used Zenoh (``assemble``, ``run
    --assemblers``), the process ends here, its output flushed, without the interpreter's
    finalization (:func:`_end_without_finalization`)."""
    code = _main(argv)
    if argv is None and "zenoh" in sys.modules:
        _end_without_finalization(code)
    return code


def _end_without_finalization(code: int) -> None:
    """Flush stdout, stderr and the log handlers, then ``os._exit(code)``. Zenoh's runtime
    threads (Rust) outlive its sessions and call into the interpreter now and then (a callback
    object dropped, a reply); one that does while the interpreter finalizes is ended by
    ``pthread_exit``, whose unwinding through Rust frames aborts the process - SIGABRT, ``FATAL:
    exception not rethrown``, exit status -6 after a complete run (an assembler in 1 of 3 fresh-clone
    CI runs at times, docs/service.md). Every command closes its files and sessions before it
    returns; nothing is left for the finalization to do but that race."""
    import logging

    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more to say
            pass
    logging.shutdown()
    os._exit(code)


def _main(argv: list[str] | None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # the top-level options (--help, --version) take no value: the first other word is the command
    first = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(first if first in COMMANDS else None)
    args = parser.parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except (ParameterError, SceneError, UsageError) as exc:
        print(f"fusion-center {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # the reader went away (``fusion-center demo | head``): no traceback; point stdout at
        # /dev/null so the interpreter's final flush does not raise again; exit as a SIGPIPE
        # death would (128 + 13)
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError):
            pass
        return 141


if __name__ == "__main__":
    sys.exit(main())
