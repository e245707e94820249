"""The command-line front ends (prsa-tune, prsa-plot, prsa-fit, prsa-bench)."""

from .._lazy import lazy_exports

_EXPORTS = {
    "DESIGN_MAX_SPEED_RAD_S": "fit",
    "EXIT_BAD_INPUT": "tune",
    "EXIT_INTERRUPTED": "tune",
    "EXIT_NUMERICAL": "tune",
    "EXIT_OK": "tune",
    "build_parser": "tune",
    "build_plot_parser": "tune",
    "cold_cli_benchmark": "bench",
    "fidelity_ladder": "bench",
    "fit_benchmark": "bench",
    "format_report": "tune",
    "main": "tune",
    "monte_carlo_benchmark": "bench",
    "parse_load_step": "tune",
    "plant_toml": "fit",
    "plot_main": "tune",
    "robust_tuning_benchmark": "bench",
    "run": "axis",
    "targets": "bench",
    "tuning_benchmark": "bench",
    "wants_axis_mode": "axis",
    "work_precision": "bench",
    "write_json_atomic": "tune",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
