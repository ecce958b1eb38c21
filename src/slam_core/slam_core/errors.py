"""User-facing errors: each names its culprit and says what to do, in one line."""

from __future__ import annotations


class SlamError(Exception):
    """Base class of errors a user can act on; str(err) is a complete one-line message."""


class BagError(SlamError):
    """A bag is missing, unreadable, corrupt or not writable."""


class TypeDefinitionError(SlamError):
    """A message type has no definition (no .msg, no Python module) in this environment."""


class ParameterError(SlamError):
    """A node parameter has an invalid value."""


class GraphError(SlamError):
    """A GRAPH file is missing or invalid."""


class DatasetError(SlamError):
    """A dataset file is missing or malformed; the message names the file and 1-based line."""
