"""The ``adalio`` command line (typer + rich).

Each area registers its own commands (``register(app)``) so that this file stays small:
``adalio.io.cli`` (info, run, config), ``adalio.sim.cli`` (simulate), ``adalio.eval.cli``
(eval, report, compare, demo). Every :class:`~adalio.errors.AdalioError` becomes one line on
stderr and a non-zero exit; Ctrl-C exits with 130 after the writers have flushed.
"""

from __future__ import annotations

import errno
import importlib
import signal
import sys
from pathlib import Path

import typer

app = typer.Typer(
    name="adalio",
    help="Adaptive LiDAR-inertial odometry for degenerate indoor scenes, straight from ROS bags.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)
"""Plain help text: flags without a ``<bool>`` type, brackets such as ``adalio[view]`` kept
literally (rich markup would drop them), nothing box-drawn to break when piped."""


@app.callback()
def _root() -> None:
    """Adaptive LiDAR-inertial odometry for degenerate indoor scenes, straight from ROS bags."""


@app.command()
def version() -> None:
    """Print the adalio version."""
    from adalio import __version__

    typer.echo(__version__)


_COMMAND_MODULES = ("adalio.io.cli", "adalio.sim.cli", "adalio.eval.cli", "adalio.batch")

for _name in _COMMAND_MODULES:
    try:
        _module = importlib.import_module(_name)
    except ModuleNotFoundError as _exc:  # an area not built yet
        if _exc.name != _name:
            raise
        continue
    _module.register(app)


_OS_HINTS = {
    errno.ENOSPC: "the disk is full",
    errno.EFBIG: "a file size limit was reached",
    errno.EDQUOT: "the disk quota is used up",
    errno.EACCES: "no permission: choose another folder",
    errno.EPERM: "no permission: choose another folder",
    errno.EROFS: "the file system is read-only: choose another folder",
    errno.ENOENT: "it does not exist: check the path",
}


def os_error_line(exc: OSError) -> str:
    """One line for an operating-system error (full disk, permissions, missing path) met while
    reading or writing: the file if known, the system's reason and what to do."""
    from adalio.errors import DISK_FULL_ERRNOS

    where = f"{exc.filename}: " if exc.filename else ""
    reason = exc.strerror or str(exc)
    hint = _OS_HINTS.get(exc.errno, "check the path, its permissions and the free disk space")
    if exc.errno in DISK_FULL_ERRNOS:
        hint += ": free space or write elsewhere (--out)"
        from adalio.sim.cache import cache_root

        cache = cache_root()
        if exc.filename is None or cache in Path(str(exc.filename)).expanduser().parents:
            hint += (f"; simulated sequences are cached in {cache} (its size cap: "
                     "$ADALIO_SIM_CACHE_GB)")
    return f"{where}{reason} ({hint})"


def main() -> None:
    """Console-script entry point: an AdalioError, a command-line usage error or an
    operating-system error (a full disk, no permission: :func:`os_error_line`) is one 'error:'
    line and exit 2; Ctrl-C at any moment is one 'interrupted' line and exit 130 (never a
    traceback)."""
    from rich.markup import escape

    from adalio.errors import AdalioError
    from adalio.term import console

    # click's base exception, found through typer's public BadParameter (typer may vendor click)
    click_error = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")
    err = console(stderr=True)
    ctrl_c = "[yellow]interrupted[/] (Ctrl-C or SIGTERM): outputs written so far are kept"
    def interrupted() -> bool:
        # a Ctrl-C that an import swallowed or turned into another error
        # (_adalio_entry.StickyInterrupt remembers it)
        return bool(getattr(signal.getsignal(signal.SIGINT), "received", False))

    try:
        try:
            code = app(standalone_mode=False)
        except AdalioError as exc:
            # after a Ctrl-C, an error that says why an import failed (the pipeline's 'the
            # estimator ... is not available') is the interrupt
            if interrupted():
                raise KeyboardInterrupt from None
            err.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False,
                      soft_wrap=True)
            sys.exit(exc.exit_code)
        except click_error as exc:
            if type(exc).__name__ != "NoArgsIsHelpError":  # that one has printed the help
                ctx = getattr(exc, "ctx", None)
                see = f" (see: {ctx.command_path} --help)" if ctx is not None else ""
                err.print(f"[bold red]error:[/] {escape(exc.format_message() + see)}",
                          highlight=False, soft_wrap=True)
            sys.exit(exc.exit_code)
        except Exception as exc:
            # after a Ctrl-C, an error from a library interrupted mid-import (numpy's C core
            # raises ImportError) is the interrupt
            if interrupted():
                raise KeyboardInterrupt from None
            if not isinstance(exc, OSError):
                raise
            err.print(f"[bold red]error:[/] {escape(os_error_line(exc))}", highlight=False,
                      soft_wrap=True)
            sys.exit(2)
        code = code if isinstance(code, int) else 0
        if interrupted():
            code = 130  # a Ctrl-C that an import swallowed
        if code == 130:  # typer turns a KeyboardInterrupt inside a command into exit 130
            err.print(ctrl_c)
        sys.exit(code)
    except (KeyboardInterrupt, typer.Abort):
        err.print(ctrl_c)
        sys.exit(130)


if __name__ == "__main__":
    main()
