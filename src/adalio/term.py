"""Rich consoles for the command line that never break a path or a command.

On a terminal, text is soft-wrapped (the terminal folds long lines, copy-paste keeps them whole)
and tables fit the window. When the output is piped or redirected, nothing is wrapped at all and
tables take their natural width, whatever ``COLUMNS`` says, so logs and scripts see each path,
command and table row on one line.
"""

from __future__ import annotations

from rich.console import Console

PIPED_WIDTH = 1000
"""Console width when not writing to a terminal (characters; wide enough for any table)."""


def console(*, stderr: bool = False) -> Console:
    """A Console on stdout (or stderr) following the rules of the module docstring."""
    con = Console(stderr=stderr, soft_wrap=True)
    if con.is_terminal:
        return con
    return Console(stderr=stderr, soft_wrap=True, width=PIPED_WIDTH)
