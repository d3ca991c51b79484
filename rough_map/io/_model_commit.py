"""Writing a model file and its card as one commit.

A model and its card must change together: a new model beside the old card fails its
sha256 check and is refused, so the old model would be lost. :func:`commit_pair` writes
both new files completely (flushed to disk) into a pending folder ``.NAME.pending/`` beside
them, then a ``complete`` marker, then renames each file into place and removes the folder.
:func:`resolve_pending`, which every save, load and card read of NAME calls first, rolls a
complete commit forward (idempotently) and deletes an incomplete one. A process killed at any
moment therefore leaves the old pair, the new pair, or a state the next access turns into
the new pair.
"""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Callable
from pathlib import Path

from rough_map._files import fsync_dir, fsync_file, write_error
from rough_map.errors import ModelError
from rough_map.io._model_archive import brief

log = logging.getLogger(__name__)

__all__ = ["MARKER", "commit_pair", "pending_folder", "resolve_pending"]

MARKER = "complete"
"""Name of the file written last into a pending folder: the commit is complete."""


def pending_folder(model_file: Path) -> Path:
    """The pending folder of a model file ``models/NAME.skops``: ``models/.NAME.pending``."""
    return model_file.with_name(f".{model_file.name[: -len('.skops')]}.pending")


def resolve_pending(model_file: Path, card_file: Path) -> None:
    """Finish or discard an interrupted commit of ``model_file`` and ``card_file``.

    Raises
    ------
    ModelError
        The pending folder cannot be resolved (permissions, a file in its place).
    """
    pending = pending_folder(model_file)
    if not pending.exists() and not pending.is_symlink():
        return
    try:
        if not pending.is_dir() or pending.is_symlink():
            raise ModelError(f"{pending}: expected a pending-commit folder; remove it by hand")
        if (pending / MARKER).is_file():
            for target in (model_file, card_file):
                staged = pending / target.name
                if staged.is_file():
                    os.replace(staged, target)
            fsync_dir(model_file.parent)
            log.info("%s: completed an interrupted save of the model and its card", model_file)
        else:
            log.warning("%s: discarded an incomplete save; the previous model stays", model_file)
        shutil.rmtree(pending)
    except OSError as err:
        raise ModelError(f"{pending}: cannot resolve an interrupted save ({brief(err)})") from err


def commit_pair(
    model_file: Path,
    card_file: Path,
    write_model: Callable[[Path], None],
    write_card: Callable[[Path], None],
) -> None:
    """Write a model file and its card together (see the module docstring).

    Parameters
    ----------
    model_file, card_file : Path
        The final files.
    write_model : callable
        ``write_model(path)`` writes the model to ``path``.
    write_card : callable
        ``write_card(path)`` writes the card to ``path`` (the staged model file is beside
        it, under the final name, to be hashed).
    """
    resolve_pending(model_file, card_file)
    pending = pending_folder(model_file)
    try:
        pending.mkdir()
    except OSError as err:
        raise write_error(model_file, err) from None
    try:
        staged_model = pending / model_file.name
        staged_card = pending / card_file.name
        write_model(staged_model)
        fsync_file(staged_model)
        write_card(staged_card)
        fsync_file(staged_card)
        marker = pending / MARKER
        marker.write_bytes(b"")
        fsync_file(marker)
        fsync_dir(pending)
    except OSError as err:  # a full disk, a read-only folder: one line naming the model
        shutil.rmtree(pending, ignore_errors=True)
        raise write_error(model_file, err) from None
    except BaseException:
        shutil.rmtree(pending, ignore_errors=True)
        raise
    resolve_pending(model_file, card_file)
