"""The ``lrm-cvx`` command: thin wrappers over the public functions.

Defaults: the recommended setting (:data:`RECOMMENDED`) wherever ``--paper`` is not
given; ``--paper`` reproduces the paper, an explicit option always wins, and a recommended
default the input cannot take falls back with one printed ``note:`` line.

Contract (docs/cli.md): every failure prints one line ``lrm-cvx <cmd>: error: ...`` on stderr
and exits with status 2 (``--debug`` also prints the traceback); no command ever writes onto
one of its inputs (globs and folders expanded, compared as resolved files); every output is
written to a temporary file beside it and renamed into place (all of ``evaluate``'s outputs
together), and an existing output is replaced only with ``--overwrite``.

The commands live beside this module, each group with its parser: ``fit`` in
:mod:`~lrm_cvx.cli_fit`, ``plan`` / ``bound`` / ``place`` / ``predict`` in
:mod:`~lrm_cvx.cli_plan`, ``evaluate`` / ``demo`` in :mod:`~lrm_cvx.cli_evaluate`, ``monitor`` in
:mod:`~lrm_cvx.cli_monitor`; the helpers they share in :mod:`~lrm_cvx.cli_common`.
"""

from __future__ import annotations

import argparse
import re
import sys
import traceback
import warnings
from collections.abc import Sequence

from .cli_common import add_common, paper_setting
from .cli_evaluate import BACKTEST_FILES, EVALUATION_FILES, add_evaluate_parsers
from .cli_fit import add_fit_parser
from .cli_monitor import add_monitor_parser
from .cli_plan import add_plan_parsers
from .errors import LrmError
from .recommended import RECOMMENDED  # the default unless --paper

__all__ = ["main", "build_parser", "RECOMMENDED", "EVALUATION_FILES", "BACKTEST_FILES"]


# ---------------------------------------------------------------------------- arguments
_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_NUM_LIST = re.compile(rf"^,?{_NUM}(?:,{_NUM})*,?$")
_COORDINATE_FLAGS = {"--start": 2, "--end": 2, "--bbox": 4}


def _join_coordinates(argv: Sequence[str]) -> list[str]:
    """``--start -10 150`` / ``--start -10,150`` -> ``--start=-10,150`` (same for ``--bbox``).

    argparse reads ``-10,150`` as an option; joining the numbers after the flag into
    ``--flag=...`` accepts every southern or western coordinate, in ``LAT LON`` or ``LAT,LON``
    form.
    """
    out: list[str] = []
    i = 0
    while i < len(argv):
        tok = argv[i]
        if tok == "--":
            out.extend(argv[i:])
            break
        n = _COORDINATE_FLAGS.get(tok)
        parts: list[str] = []
        j = i + 1
        while n is not None and j < len(argv) and len(parts) < n and _NUM_LIST.match(argv[j]):
            parts += [v for v in argv[j].split(",") if v]
            j += 1
        if parts:
            out.append(f"{tok}={','.join(parts)}")
            i = j
        else:
            out.append(tok)
            i += 1
    return out


# ---------------------------------------------------------------------------- parser
class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``lrm-cvx fit: error: ...`` and exit status 2."""

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    """The ``lrm-cvx`` parser: every command with its options, in the order ``--help`` lists."""
    parser = _Parser(
        prog="lrm-cvx",
        description="Persistent environmental monitoring with low-rank models: fit a GLRM, plan "
        "a sampling route, certify it, predict the map, evaluate like the paper. Every default "
        "is the recommended setting (docs/reconstruction.md); --paper reproduces the paper's "
        "setting, and an explicit option always wins.")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    parser.add_argument("--debug", action="store_true",
                        help="print the traceback of an error (for bug reports)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    add_fit_parser(sub)
    add_plan_parsers(sub)  # plan, bound, place, predict
    add_evaluate_parsers(sub)  # evaluate, demo
    add_monitor_parser(sub)  # monitor init|plan|replan|export|assimilate|map
    for action in sub.choices.values():
        add_common(action)
    return parser


# ---------------------------------------------------------------------------- main
def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _describe(exc: BaseException) -> str:
    if isinstance(exc, LrmError):
        return _one_line(str(exc))
    if isinstance(exc, OSError) and exc.strerror:
        where = f": {exc.filename}" if exc.filename else ""
        return _one_line(f"{exc.strerror}{where}")
    if isinstance(exc, OSError):
        return _one_line(str(exc))
    return _one_line(f"unexpected {type(exc).__name__}: {exc} (rerun with --debug for the "
                     "traceback and report it)")


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``lrm-cvx`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        parser = build_parser()
        args = parser.parse_args(_join_coordinates(argv))
    except SystemExit as exc:  # --help (0) or a one-line usage error (2)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    except KeyboardInterrupt:
        print("lrm-cvx: interrupted", file=sys.stderr)
        return 130
    prefix = " ".join(["lrm-cvx", args.command]
                      + ([args.monitor_command] if args.command == "monitor" else []))

    def show(message, category, filename, lineno, file=None, line=None):
        print(f"{prefix}: warning: {_one_line(str(message))}", file=sys.stderr)

    with warnings.catch_warnings():
        warnings.showwarning = show
        try:
            paper_setting(args)  # --paper --recommended: one line before any work
            return int(args.func(args) or 0)
        except KeyboardInterrupt:
            print(f"{prefix}: interrupted", file=sys.stderr)
            return 130
        except Exception as exc:  # every failure: one line, exit 2 (traceback with --debug)
            if args.debug:
                traceback.print_exc()
            print(f"{prefix}: error: {_describe(exc)}", file=sys.stderr)
            return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
