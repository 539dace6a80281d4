"""The ptm_ros error family. The library raises these; only command-line tools turn them into exit codes."""

from __future__ import annotations


class PtmError(Exception):
    """Base class of every error raised on purpose by ptm_ros."""


class ConfigError(PtmError):
    """A parameter file or a parameter value is malformed or out of range."""


class ModelError(PtmError):
    """A model was given inputs it cannot evaluate (wrong shapes, non-finite values, N too large)."""


class DataError(PtmError):
    """Input data (a log, a bag, a message, a ground-truth file) is malformed or inconsistent."""


class BagError(DataError):
    """A rosbag2 cannot be read or written (missing, corrupt, lacking a required topic)."""


class RegistrationError(PtmError):
    """Scan registration could not run (e.g. empty point clouds)."""
