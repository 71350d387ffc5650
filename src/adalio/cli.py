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


def main() -> None:
    """Console-script entry point."""
    from adalio.errors import AdalioError
    from adalio.term import console

    err = console(stderr=True)
    try:
        app(standalone_mode=True)
    except AdalioError as exc:
        err.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
        sys.exit(exc.exit_code)
    except (KeyboardInterrupt, typer.Abort):
        err.print("[yellow]interrupted[/]: partial outputs were flushed")
        sys.exit(130)


if __name__ == "__main__":
    main()
