"""The ``linegs-gpu`` command that ``pip install .`` installs: the command line compiled
into the native module (the same code as the ``linegs-gpu`` binary), run on ``sys.argv``."""

import signal
import sys

from . import _linegs


def main() -> None:
    # Ctrl-C stops the command as it stops the binary (Python's handler would only set a
    # flag that the native code never looks at).
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    sys.exit(_linegs.main(sys.argv))
