"""The ``linegs-gpu`` command that ``pip install .`` installs: the command line compiled
into the native module (the same code as the ``linegs-gpu`` binary), run on ``sys.argv``.
A module built without the binding's ``cli`` feature has no command line; the command
then says so and exits 2."""

import signal
import sys

from . import _linegs


def main() -> None:
    run = getattr(_linegs, "main", None)
    if run is None:
        sys.stderr.write(
            "error: this build of the linegs module has no command line (the binding was "
            "built without its `cli` feature); install with `pip install .` from the "
            "repository, or use the `linegs-gpu` binary of `cargo build --release`\n"
        )
        sys.exit(2)
    # Ctrl-C stops the command as it stops the binary (Python's handler would only set a
    # flag that the native code never looks at).
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    sys.exit(run(sys.argv))
