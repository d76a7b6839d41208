"""One exception hierarchy for collabslam (evo's EvoException pattern).

At the CLI, a `CollabSlamError` becomes one log line and exit code 1; anything
else is logged with a traceback.
"""


class CollabSlamError(Exception):
    """Base of every error collabslam raises on purpose."""


class ConfigError(CollabSlamError):
    """A configuration value is missing, of the wrong type or out of range."""


class ProtocolError(CollabSlamError):
    """A message could not be decoded or failed validation."""


class FileFormatError(CollabSlamError):
    """A file (map, trajectory, log) does not have the expected format."""


class ProcessError(CollabSlamError):
    """A supervised child process failed."""


class PersistenceError(CollabSlamError):
    """The base station's database cannot be opened, read or written."""


class TooFewPoints(CollabSlamError):
    """A scan matcher's target without the points to match against (a 3-D robot's
    keyframes, a laser that saw nothing): the match is not tried, which is no fault."""
