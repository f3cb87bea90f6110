"""surfstream's exceptions and warning category.

The compiled module raises these by name (src/lib.rs, ``Kind``), with the message the CLI
prints after ``surfstream: error:``.
"""


class Error(Exception):
    """Any surfstream failure; the message is the CLI's for the same failure."""


class PathError(Error, FileNotFoundError):
    """The path does not exist (or is a folder where a file was expected)."""


class FormatError(Error):
    """An unsupported file extension, or a file whose contents its reader refuses."""


class ParameterError(Error, ValueError):
    """An argument out of range: a pitch, a cutoff, a wavelet name, a mesh tolerance."""


class CliError(Error):
    """A graph run or stitch (run by the ``surfstream`` CLI binary) failed, or no binary found."""


class SurfstreamWarning(UserWarning):
    """What a reader or an algorithm accepted but the user should know (the CLI's warnings)."""
