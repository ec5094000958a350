"""Exceptions with one-line messages meant for users; the CLI prints them without traceback."""


class RRTCoLearnError(Exception):
    """Base class: a problem with the user's input, files or configuration."""

    exit_code = 2


class ConfigError(RRTCoLearnError):
    """An invalid configuration value or key."""


class ArtefactError(RRTCoLearnError):
    """A missing, truncated, tampered or incompatible file."""


class EnvironmentProblem(RRTCoLearnError):
    """Something the machine lacks, such as an optional dependency."""

    exit_code = 3
