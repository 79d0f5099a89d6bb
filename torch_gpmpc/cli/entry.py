"""The ``gpmpc`` entry point: parse, run the command's module, turn user errors into one line.

Each command's work is ``main(args)`` in its own module of this package.
"""

from __future__ import annotations

import errno
import importlib
import logging
import sys
import warnings

from torch_gpmpc.cli import collector
from torch_gpmpc.cli.parser import build_parser
from torch_gpmpc.errors import GpmpcError

#: OSError numbers without a file name that are still the user's storage: disk full, quota, read-only.
_STORAGE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS)

# command -> module holding its main(args)
_COMMANDS = {
    "collect": "torch_gpmpc.cli.collect",
    "fit-gp": "torch_gpmpc.cli.fit_gp",
    "tune": "torch_gpmpc.cli.tune",
    "run": "torch_gpmpc.cli.run",
    "reproduce": "torch_gpmpc.cli.reproduce",
    "bench": "torch_gpmpc.cli.bench",
    "calibrate": "torch_gpmpc.cli.calibrate",
    "benchmark": "torch_gpmpc.cli.benchmark",
    "keys": "torch_gpmpc.cli.keys",
}



def main(argv: list[str] | None = None) -> int:
    """Run one ``gpmpc`` command (``argv``, default ``sys.argv[1:]``); returns the exit code. The console
    script calls it through :func:`console_main`."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:  # a bare `gpmpc`: what it can do
        parser.print_help()
        return 0
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if args.threads < 1:
        print(f"gpmpc: error: --threads must be >= 1, got {args.threads}", file=sys.stderr)
        return 2
    try:
        with collector.setup_phase():  # torch and the command's modules live until the process ends
            import torch

            module = importlib.import_module(_COMMANDS[args.command])
        torch.set_num_threads(args.threads)
        with warnings.catch_warnings():  # restores the warning display when main() returns to a caller
            if not args.debug:
                warnings.showwarning = _one_line_warning(args.command)
            code = module.main(args)
    except GpmpcError as exc:
        if args.debug:
            raise
        print(f"gpmpc {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # unwritable/unreadable path, disk full: the user's environment, not a bug
        if args.debug or (exc.filename is None and exc.errno not in _STORAGE_ERRNOS):
            raise  # e.g. a network error of the distributed backend: keep its traceback
        where = f" {exc.filename!r}" if exc.filename else ""
        why = ("a part of the path is an existing file, not a directory"
               if isinstance(exc, (FileExistsError, NotADirectoryError)) else exc.strerror or str(exc))
        print(f"gpmpc {args.command}: error: cannot access{where}: {why}; "
              "check the path and its permissions", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"gpmpc {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(code or 0)


def _one_line_warning(command: str):
    """A ``warnings.showwarning`` that prints ``gpmpc <command>: warning: <message>``, one line like the
    errors (``--debug`` keeps Python's form, with the file and line that warned)."""
    def show(message, category, filename, lineno, file=None, line=None) -> None:
        print(f"gpmpc {command}: warning: {message}", file=file or sys.stderr)
    return show


def console_main() -> None:
    """The console script ``gpmpc``: :func:`main` in a process it owns, so the command may tune the
    process's garbage collector (:mod:`~torch_gpmpc.cli.collector`); exits with its code."""
    collector.own_process()
    code = main()
    collector.skip_final_collection()
    sys.exit(code)


if __name__ == "__main__":  # pragma: no cover
    console_main()
