"""Figures from result objects."""

from .._lazy import lazy_exports

_EXPORTS = {
    "baseline_pairs_plot": "loop",
    "binding_level": "loop",
    "bode_loop": "loop",
    "bode_plant": "loop",
    "contact_force_plot": "loop",
    "design_figures": "loop",
    "duty_cycle_comparison": "loop",
    "duty_cycle_pairs_plot": "loop",
    "duty_cycle_plot": "loop",
    "gain_study_plot": "loop",
    "load_step_comparison": "loop",
    "load_step_plot": "loop",
    "save_figure": "loop",
    "sensitivity_plot": "loop",
    "step_response_plot": "loop",
    "tuning_landscape": "loop",
    "write_design_plots": "loop",
    "write_standard_plots": "loop",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
