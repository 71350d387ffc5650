"""User-facing errors.

Every problem caused by the user's input (a bag, a config, a flag) is raised as an
:class:`AdalioError` whose message is one line: what is wrong, where (file / topic / field /
key) and what to do. The CLI prints it and exits non-zero, never with a traceback.
"""

from __future__ import annotations

import errno
from collections.abc import Iterator
from contextlib import contextmanager

DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EFBIG, errno.EDQUOT)
"""Operating-system errors of a write that found no room (full disk, file size limit, quota)."""


class AdalioError(Exception):
    """Base class of all user-facing errors; ``str(err)`` is a one-line message."""

    exit_code = 2


class ConfigError(AdalioError):
    """A config file, preset or command-line override is invalid."""


class BagError(AdalioError):
    """A bag cannot be read, or its topics / messages / fields are unusable."""


class InputError(AdalioError):
    """Data handed to the estimator or a tool is malformed (shapes, stamps, coverage)."""


@contextmanager
def writing_to(path: object) -> Iterator[None]:
    """Name ``path`` (the output being written) in an ``OSError`` of a full disk that carries
    no file name of its own (e.g. a library's buffered write), so that the CLI's one line says
    where it happened."""
    try:
        yield
    except OSError as exc:
        if exc.filename is None and exc.errno in DISK_FULL_ERRNOS:
            exc.filename = str(path)
        raise
