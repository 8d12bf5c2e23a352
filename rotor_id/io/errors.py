"""
Exceptions and warnings of the input layer.

Every error message names the file or topic, what is wrong and what to do about it, so that a
user who only sees the message can act on it.
"""


class BagError(ValueError):
    """A rosbag2 recording cannot be read into a :class:`~rotor_id.io.record.Record`."""


class RunDescriptionError(ValueError):
    """
    A run-description YAML file is malformed or inconsistent.

    Attributes
    ----------
    path
        The file (or ``'<string>'``) the description came from.
    line
        1-based line number of the offending key, or ``None`` if unknown.

    """

    def __init__(self, message: str, path: str | None = None, line: int | None = None) -> None:
        super().__init__(message)
        self.path = path
        self.line = line


class RunDescriptionWarning(UserWarning):
    """A run description contains something that is ignored (e.g. an unknown key)."""


class BagWarning(UserWarning):
    """A recording was read, but samples were dropped, sorted, repaired or recovered."""
