"""The ``adalio`` command line (typer + rich).

Each area registers its own commands (``register(app)``) so that this file stays small:
``adalio.io.cli`` (info, run, config), ``adalio.sim.cli`` (simulate), ``adalio.eval.cli``
(eval, report, compare, demo). Every :class:`~adalio.errors.AdalioError` becomes one line on
stderr and a non-zero exit; Ctrl-C exits with 130 after the writers have flushed.
"""

from __future__ import annotations

import importlib
import sys

import typer
from rich.console import Console

app = typer.Typer(
    name="adalio",
    help="Adaptive LiDAR-inertial odometry for degenerate indoor scenes, straight from ROS bags.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root() -> None:
    """Adaptive LiDAR-inertial odometry for degenerate indoor scenes, straight from ROS bags."""


@app.command()
def version() -> None:
    """Print the adalio version."""
    from adalio import __version__

    typer.echo(__version__)


_COMMAND_MODULES = ("adalio.io.cli", "adalio.sim.cli", "adalio.eval.cli")

for _name in _COMMAND_MODULES:
    try:
        _module = importlib.import_module(_name)
    except ModuleNotFoundError as _exc:  # an area not built yet
        if _exc.name != _name:
            raise
        continue
    _module.register(app)


def _from_ctrl_c(exc: BaseException | None) -> bool:
    """True if ``exc`` was raised while handling a KeyboardInterrupt (typer turns one inside a
    command into a silent exit 130)."""
    while exc is not None:
        if isinstance(exc, KeyboardInterrupt):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


def main() -> None:
    """Console-script entry point: an AdalioError is one 'error:' line and exit 2; Ctrl-C at any
    moment is one 'interrupted' line and exit 130 (never a traceback)."""
    from adalio.errors import AdalioError

    err = Console(stderr=True)
    ctrl_c = "[yellow]interrupted[/] (Ctrl-C): outputs written so far are kept"
    try:
        try:
            app(standalone_mode=True)
        except AdalioError as exc:
            err.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
            sys.exit(exc.exit_code)
        except SystemExit as exc:
            if exc.code == 130 and _from_ctrl_c(exc):
                err.print(ctrl_c)
            raise
    except (KeyboardInterrupt, typer.Abort):
        err.print(ctrl_c)
        sys.exit(130)


if __name__ == "__main__":
    main()
