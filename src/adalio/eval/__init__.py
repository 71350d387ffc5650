"""Evaluation: ATE / RPE via evo, the HILTI 2022 score, figures, run reports, mode comparison.

Modules: ``metrics`` (ate, rpe, align_pair), ``hilti`` (hilti_score), ``plots``, ``report``
(make_report), ``compare`` (compare_modes), ``demo`` (run_demo), ``files`` (readers), ``cli``.
"""

from typing import Any

_LAZY = {"ate": "adalio.eval.metrics", "rpe": "adalio.eval.metrics",
         "hilti_score": "adalio.eval.hilti"}


def __getattr__(name: str) -> Any:
    """evo (and with it matplotlib) is imported on first use, not when the CLI registers."""
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'adalio.eval' has no attribute {name!r}")


__all__ = ["ate", "hilti_score", "rpe"]
