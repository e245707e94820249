"""The command-line front ends (prsa-tune, prsa-plot, prsa-fit, the Monte-Carlo replay); the benchmarks
are outside the package (``python benchmarks/bench.py``)."""

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
    "format_move_report": "report",
    "format_report": "report",
    "format_robust": "report",
    "main": "tune",
    "parse_load_step": "inputs",
    "plant_toml": "fit",
    "plot_main": "plot",
    "run": "axis",
    "wants_axis_mode": "axis",
    "write_json_atomic": "common",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
