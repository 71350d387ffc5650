"""User-facing errors.

Every problem caused by the user's input (a bag, a config, a flag) is raised as an
:class:`AdalioError` whose message is one line: what is wrong, where (file / topic / field /
key) and what to do. The CLI prints it and exits non-zero, never with a traceback.
"""

from __future__ import annotations


class AdalioError(Exception):
    """Base class of all user-facing errors; ``str(err)`` is a one-line message."""

    exit_code = 2


class ConfigError(AdalioError):
    """A config file, preset or command-line override is invalid."""


class BagError(AdalioError):
    """A bag cannot be read, or its topics / messages / fields are unusable."""


class InputError(AdalioError):
    """Data handed to the estimator or a tool is malformed (shapes, stamps, coverage)."""
