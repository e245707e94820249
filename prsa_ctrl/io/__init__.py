"""What leaves the toolkit: drive files, code export (C, Structured Text), and the all-or-nothing output writer."""

from .._lazy import lazy_exports

_EXPORTS = {
    "CODE_SUFFIXES": "codegen",
    "DISCRETISATIONS": "export",
    "DriveLaw": "codegen",
    "FILTER_PLACES": "export",
    "FORMATS": "export",
    "OutputError": "output",
    "PositionLaw": "codegen",
    "REAL_TYPES": "codegen",
    "ReferenceLaw": "codegen",
    "TEMP_MARK": "output",
    "Transaction": "output",
    "c_code": "codegen",
    "check_code_export": "codegen",
    "check_directory": "output",
    "check_distinct": "output",
    "check_writable": "output",
    "cleanup_temporaries": "output",
    "code_files": "codegen",
    "code_texts": "codegen",
    "drive_law": "codegen",
    "dumps": "export",
    "export_code": "codegen",
    "export_controller": "export",
    "json_safe": "output",
    "live_temporaries": "output",
    "make_directory": "output",
    "package_roots": "output",
    "pid_biquad": "export",
    "remove_created": "output",
    "replay_inputs": "codegen",
    "simulated_biquad": "export",
    "st_code": "codegen",
    "write_code_export": "codegen",
    "write_file": "output",
    "write_text": "output",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
