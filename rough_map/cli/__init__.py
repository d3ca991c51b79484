"""Command-line interface. Thin: each module wires library stages together.

Every command module exposes ``register(subparsers)`` that adds its parser and sets
``func`` to a callable taking the parsed ``argparse.Namespace`` and returning an exit code.
Data goes to stdout; logs and progress bars go to stderr.
"""
