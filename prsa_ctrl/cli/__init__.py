"""The command-line front ends (prsa-tune, prsa-plot, prsa-fit, prsa-bench, the Monte-Carlo replay)."""

from .._lazy import lazy_exports

_EXPORTS = {
    "DESIGN_MAX_SPEED_RAD_S": "fit",
    "EXIT_BAD_INPUT": "common",
    "EXIT_INTERRUPTED": "common",
    "EXIT_NUMERICAL": "common",
    "EXIT_OK": "common",
    "EXIT_TERMINATED": "common",
    "MOVE_FLAGS": "tune",
    "build_parser": "tune",
    "build_plot_parser": "plot",
    "cold_cli_benchmark": "bench",
    "fidelity_ladder": "bench",
    "fit_benchmark": "bench",
    "format_move_report": "report",
    "format_report": "report",
    "format_robust": "report",
    "main": "tune",
    "monte_carlo_benchmark": "bench",
    "parse_load_step": "inputs",
    "plant_toml": "fit",
    "plot_main": "plot",
    "robust_tuning_benchmark": "bench",
    "run": "axis",
    "targets": "bench",
    "tuning_benchmark": "bench",
    "wants_axis_mode": "axis",
    "work_precision": "bench",
    "write_json_atomic": "common",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
