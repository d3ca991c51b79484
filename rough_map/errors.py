"""The one error hierarchy of rough_map.

Every error raised on purpose by the library is a :class:`RoughMapError`. Subclasses also
inherit the builtin they resemble, so ``except ValueError`` keeps working for callers that
do not know rough_map.
"""

from __future__ import annotations

from pathlib import Path


class RoughMapError(Exception):
    """Root of all rough_map errors."""


class InputError(RoughMapError, ValueError):
    """An argument or an array has the wrong value, shape, units or content."""


class UnknownOptionError(InputError, TypeError):
    """An unknown keyword option (a TypeError too, as Python raises for a bad keyword)."""


class PatchError(InputError):
    """A patch cannot be analysed (too few points, too many gaps, ...)."""


class FileFormatError(RoughMapError, ValueError):
    """A file could not be read: unknown type, truncated, wrong fields.

    Parameters
    ----------
    path : str or Path
        The file concerned.
    message : str
        What is wrong.
    field : str, optional
        The field, column, topic or key concerned.
    """

    def __init__(self, path: str | Path, message: str, field: str | None = None) -> None:
        self.path = Path(path)
        self.field = field
        self._parts = (str(path), message, field)
        where = f"{path}" + (f" [{field}]" if field else "")
        super().__init__(f"{where}: {message}")

    def __reduce__(self) -> tuple:
        # Rebuilt from its parts, so that an error raised in a worker process (joblib,
        # multiprocessing) reaches the parent as itself, not as an unpickling failure.
        return (type(self), self._parts, self.__dict__)


class SchemaError(FileFormatError):
    """A traverse or configuration file does not follow its schema."""


class ModelError(RoughMapError, ValueError):
    """A model file is missing, foreign, tampered with, or does not fit the data."""


class NotFittedError(RoughMapError, AttributeError):
    """An estimator was used before ``fit``."""


class RoughMapWarning(UserWarning):
    """Root of rough_map's warnings."""


class EmptyMapWarning(RoughMapWarning):
    """A traverse gave no valid patch: the map is all nodata."""
