"""Console entry point of ``adalio``, outside the package so that it loads before anything else:
Ctrl-C while the command line is still being imported (numpy, typer, ...) exits 130 with one
line instead of a traceback, also where the interrupt surfaces as another error from an
extension being imported. Everything else is :func:`adalio.cli.main`.

Ctrl-C is also remembered, not only raised: some libraries wrap their optional imports in
``except BaseException`` (or a bare ``except``), which swallows the KeyboardInterrupt raised
while they are being imported, and the command would then run to the end and exit 0. The
handler installed here keeps ``received`` set; :func:`adalio.cli.main` and the run's Ctrl-C guard
(``adalio.pipeline``) read it from whatever handler is installed, and stop with exit 130."""

import signal
import sys


class StickyInterrupt:
    """SIGINT handler: raise KeyboardInterrupt, as Python's default handler does, and remember
    that it happened (``received``) in case the exception is swallowed."""

    def __init__(self) -> None:
        self.received = False
        self._report = sys.unraisablehook

    def __call__(self, signum: int, frame: object) -> None:
        self.received = True
        raise KeyboardInterrupt

    def unraisable(self, report: object) -> None:
        """``sys.unraisablehook``: a KeyboardInterrupt raised where Python cannot raise (inside a
        weakref callback, such as importlib's module-lock cleanup, or a ``__del__``) is dropped
        after this handler remembered it; Python would print 'Exception ignored in ...' and a
        traceback beside the 'interrupted' line. Anything else is reported as before."""
        if self.received and isinstance(getattr(report, "exc_value", None), KeyboardInterrupt):
            return
        self._report(report)


def as_ctrl_c(signum: int, frame: object) -> None:
    """SIGTERM handler (``timeout``, a batch system's time limit, ``docker stop``, systemd):
    a Ctrl-C, delivered to whatever SIGINT handler is installed at the time, so the run stops
    after its current scan and keeps its outputs (map, scans.csv, config.yaml; a batch's
    summary) as after Ctrl-C, with exit 130."""
    import os

    os.kill(os.getpid(), signal.SIGINT)


def main() -> None:
    """Run the adalio command line."""
    handler = StickyInterrupt()
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, handler)
        sys.unraisablehook = handler.unraisable
    if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, as_ctrl_c)
    try:
        from adalio.cli import main as cli_main
    except KeyboardInterrupt:
        handler.received = True
    except Exception:
        # a Ctrl-C inside an extension's import can surface as another error: numpy, hit while
        # importing its C core, raises ImportError (PyCapsule_Import could not import module
        # "datetime"); after a Ctrl-C that is the interrupt, not a broken install
        if not handler.received:
            raise
    if handler.received:
        sys.stderr.write("interrupted\n")
        raise SystemExit(130) from None
    cli_main()
