"""Command-line interface. Thin: each module wires library stages together.

Every command module exposes ``register(subparsers)`` that adds its parser and sets
``func`` to a callable taking the parsed ``argparse.Namespace`` and returning an exit code.
Data goes to stdout; logs and progress bars go to stderr.
"""

import os as _os
import signal as _signal
import sys as _sys

# Run as the rough-map command, SIGINT is blocked from the first import until main() runs:
# the threads the libraries start meanwhile (BLAS pools) inherit the block, so a Ctrl-C
# always reaches the main thread. Without it one could land on a BLAS thread while the
# workers start (SIGINT ignored then, rough_map.features.frames.children_ignore_sigint)
# and be lost. main() unblocks it in the main thread only (rough_map.cli.main).
_COMMAND = _sys.argv[0] if _sys.argv else ""
if _os.path.basename(_COMMAND) == "rough-map" or _COMMAND.endswith(
    _os.path.join("rough_map", "__main__.py")
):
    _signal.pthread_sigmask(_signal.SIG_BLOCK, {_signal.SIGINT})
