"""Evaluation: ATE / RPE via evo, the HILTI 2022 score, figures, run reports, mode comparison.

Modules: ``metrics`` (ate, rpe, align_pair), ``hilti`` (hilti_score), ``plots``, ``report``
(make_report), ``compare`` (compare_modes), ``demo`` (run_demo), ``files`` (readers), ``cli``.
"""

from adalio.eval.hilti import hilti_score
from adalio.eval.metrics import ate, rpe

__all__ = ["ate", "hilti_score", "rpe"]
