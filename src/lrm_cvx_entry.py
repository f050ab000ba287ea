"""The ``lrm-cvx`` console script, kept outside the package so that it starts instantly.

Importing :mod:`lrm_cvx` loads numpy, xarray and (later) numba, about a second; a Ctrl-C in that
second would otherwise print a traceback and kill the process by the signal. Here the import
runs inside the handler: Ctrl-C at any moment prints ``lrm-cvx: interrupted`` and exits 130.
"""

from __future__ import annotations

import signal
import sys


def main() -> int:
    """Import the command line and run it; Ctrl-C during the import exits 130 with one line."""
    try:
        from lrm_cvx.cli import main as run
    except KeyboardInterrupt:
        print("lrm-cvx: interrupted", file=sys.stderr)
        return 130
    status = run()
    # the command has finished (its own Ctrl-C handling gave 130): a Ctrl-C while the
    # interpreter shuts down must not turn the result into a death by signal
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    return status


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
