"""The text reports of ``prsa-tune`` and ``prsa-plot``, kept importable here: they moved to
:mod:`prsa_ctrl.studies.scenereport`, where each scene kind's report
(:mod:`prsa_ctrl.studies.scenekinds`) formats itself."""

from __future__ import annotations

from ..studies.scenereport import (beaten_text, diff_text, fmt, fmt_margin, format_friction_ff, format_move_report,
                                   format_report, format_robust, pct_text, scene_header, table)

__all__ = ["format_report", "format_robust", "format_move_report", "fmt", "fmt_margin", "table", "scene_header",
           "pct_text", "diff_text", "beaten_text", "format_friction_ff"]
