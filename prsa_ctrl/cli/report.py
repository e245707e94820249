"""Deprecated alias: the text reports of ``prsa-tune`` and ``prsa-plot`` moved to
:mod:`prsa_ctrl.studies.scenereport`, where each scene kind's report
(:mod:`prsa_ctrl.studies.scenekinds`) formats itself. Every name read here warns
(``DeprecationWarning``); ``prsa_ctrl.cli``'s names of them (``prsa_ctrl.cli.format_report``, ...)
are the report module's own."""

from __future__ import annotations

import warnings
from typing import Any

__all__ = ["format_report", "format_robust", "format_move_report", "fmt", "fmt_margin", "table", "scene_header",
           "pct_text", "diff_text", "beaten_text", "format_friction_ff"]


def __getattr__(name: str) -> Any:
    if name not in __all__:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    warnings.warn(f"prsa_ctrl.cli.report is deprecated; import {name} from prsa_ctrl.studies.scenereport",
                  DeprecationWarning, stacklevel=2)
    from ..studies import scenereport

    return getattr(scenereport, name)
