"""Exceptions with messages meant for users: they name the file, topic or field at fault."""


class VingsError(Exception):
    """Base class of every error VINGS reports to the user (the CLI prints it without a traceback)."""


class InputError(VingsError):
    """Bad input data: missing file, unknown encoding, corrupt image, bad timestamps, ..."""


class ConfigError(VingsError):
    """Unknown or invalid parameter in a params file or on the command line."""


class TrackingLost(VingsError):
    """The front end lost track (too few confident pixels, divergence)."""
