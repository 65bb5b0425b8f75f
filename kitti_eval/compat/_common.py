"""What the drop-ins share: they return numbers and text as the frameworks do, so what the evaluation has to
say about the input (boxes whose size is not positive, frames without predictions, ...) is said as Python
warnings, which the frameworks' logs and test runners show."""

from __future__ import annotations

import warnings

from ..core.result import EvalResult

__all__ = ["warn_about"]


def warn_about(result: EvalResult) -> None:
    """Each of ``result.warnings`` as a :class:`UserWarning` attributed to the drop-in's caller."""
    for message in result.warnings:
        warnings.warn(message, UserWarning, stacklevel=3)
