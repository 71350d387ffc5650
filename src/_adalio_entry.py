"""Console entry point of ``adalio``, outside the package so that it loads before anything else:
Ctrl-C while the command line is still being imported (numpy, typer, ...) exits 130 with one
line instead of a traceback. Everything else is :func:`adalio.cli.main`."""

import sys


def main() -> None:
    """Run the adalio command line."""
    try:
        from adalio.cli import main as cli_main
    except KeyboardInterrupt:
        sys.stderr.write("interrupted\n")
        raise SystemExit(130) from None
    cli_main()
