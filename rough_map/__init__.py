"""rough_map: how rough is the ground ahead, what kind of ground it is, and where.

The data flows one way::

    io -> patch -> psd -> classify -> filter -> map -> export

``cli`` wires the stages together; nothing in the library imports it.
"""

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
