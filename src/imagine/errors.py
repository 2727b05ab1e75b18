"""User-facing errors.

Everything a user can get wrong (a config value, a file, a folder, an action) raises a subclass of
:class:`ImagineError` with a one-line message that names the problem. The command line prints that
line and exits non-zero, never a traceback.
"""


class ImagineError(Exception):
    """Base class of every error whose message is meant for the user, as one line."""


class ConfigError(ImagineError, ValueError):
    """A configuration value, or a combination of values, is invalid."""


class ObservationError(ImagineError, ValueError):
    """An observation handed to an agent (``Agent.act``) is not of the shape or type it acts on."""


class FragmentFolderError(ImagineError):
    """A folder of fragment photographs does not follow the documented layout."""


class DatasetFileError(ImagineError):
    """A dataset file is missing, truncated or not one that `imagine dataset` wrote."""


class CheckpointError(ImagineError):
    """A checkpoint is missing, truncated, corrupt or of another architecture."""


class NumericalError(ImagineError):
    """A loss became NaN or infinite: the run stops, naming the network and the step."""


class Interrupted(ImagineError):
    """SIGINT or SIGTERM stopped a run after it wrote a checkpoint; rerun to resume."""

    def __init__(self, message: str, signal_number: int) -> None:
        super().__init__(message)
        self.signal_number = signal_number

    def __reduce__(self):  # a worker process's stop reaches its parent whole
        return (type(self), (str(self), self.signal_number))


class FolderInUse(ImagineError):
    """Another live process is running jobs in this folder (its lock names the process)."""
