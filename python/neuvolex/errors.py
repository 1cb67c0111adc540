"""The exceptions neuvolex raises, one base class and one subclass per kind of failure.

Every class also derives from the builtin exception the package raised before it had its own
(``ValueError``, ``FileNotFoundError``, ``RuntimeError``, ``KeyboardInterrupt``), so code
written against those keeps working. The native module maps the Rust library's error types
onto them: a store's held writer lock is :class:`LockError`, a file or store that cannot be
read is :class:`FileError`, a refused argument is :class:`ArgumentError`, and Ctrl-C (or a
progress callback raising ``KeyboardInterrupt``) is :class:`Cancelled`.
"""

from __future__ import annotations

__all__ = [
    "Error",
    "ArgumentError",
    "FileError",
    "MissingFileError",
    "LockError",
    "Cancelled",
    "NeuvolexRuntimeError",
]


class Error(Exception):
    """The base class of every neuvolex exception (Ctrl-C's :class:`Cancelled` included)."""


class ArgumentError(Error, ValueError):
    """An argument or input array was refused; the message names the argument."""


class FileError(Error, ValueError):
    """A volume file or brick store cannot be read or used; the message names it."""


class MissingFileError(FileError, FileNotFoundError):
    """A volume file or store that does not exist."""


class LockError(Error, RuntimeError):
    """Another process holds the store's writer lock (the message names the holder)."""


class Cancelled(Error, KeyboardInterrupt):
    """The work was cancelled (Ctrl-C): it stopped at its next brick; the store stays usable."""


class NeuvolexRuntimeError(Error, RuntimeError):
    """Reading, writing or computing failed for another reason."""
