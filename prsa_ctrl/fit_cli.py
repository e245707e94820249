"""``prsa-fit``: calibrate a plant file from measured drive data, or design the experiment.

``prsa-fit [DATA.csv ...] [--frf FRF.csv ...] --out MY.toml [--json REPORT.json] [--plots DIR]
[--plant BASE] [--fit KEY,...] [--fidelity rigid|compliant] [--validate OTHER.csv ...]
[--columns name=header,...] [--torque-constant KT] [--load N] [--frf-speed RAD_S] [--frf-load N]
[--coherence-min C] [--delay-samples N]``

``prsa-fit --design multisine|chirp|steps --out excitation.csv [--duration S] [--sample-time S]
[--f-min HZ] [--f-max HZ] [--amplitude A] [--offset A]``

Exit codes: 0 success, 2 bad input (one line naming the value), 3 the fit did not converge.
Output paths are checked before the fit; every file is written atomically.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path
from typing import Sequence

from .errors import PlantFileError

__all__ = ["main", "build_parser", "plant_toml"]


class _UsageError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2, no usage dump
        raise _UsageError(message)


def _number(flag: str, positive: bool = True):
    def conv(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} {text!r}: expected a number") from None
        if not math.isfinite(v) or (positive and v <= 0):
            raise argparse.ArgumentTypeError(f"{flag} {text!r}: expected a finite number{' > 0' if positive else ''}")
        return v

    return conv


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="prsa-fit", description="Fit a plant file to measured drive data (grey-box, with 95 % CIs), "
                "or write an excitation signal for the experiment.")
    p.add_argument("data", nargs="*", metavar="DATA.csv", help="time-domain records to fit")
    p.add_argument("--out", required=True, metavar="PATH", help="output plant .toml (or excitation .csv with --design)")
    p.add_argument("--json", metavar="PATH", help="JSON report")
    p.add_argument("--frf", nargs="+", default=[], metavar="FRF.csv", help="frequency responses torque command -> "
                   "nut speed (frequency_hz, magnitude_db, phase_deg[, coherence] or real, imag): fitted alone "
                   "without DATA.csv, otherwise used to validate the fit")
    p.add_argument("--frf-speed", type=_number("--frf-speed", positive=False), default=30.0, metavar="RAD_S",
                   help="nut speed during the FRF measurement, rad/s (default 30)")
    p.add_argument("--frf-load", type=_number("--frf-load", positive=False), default=None, metavar="N",
                   help="axial load during the FRF measurement, N (default --load, else 0)")
    p.add_argument("--coherence-min", type=_number("--coherence-min", positive=False), default=0.8, metavar="C",
                   help="FRF points with a lower coherence are dropped (default 0.8)")
    p.add_argument("--plots", metavar="DIR", help="write residual, overlay and Bode figures (PNG) into DIR "
                   "(created if missing)")
    p.add_argument("--plant", default=None, metavar="NAME|PATH", help="base plant (default paper-iprsm)")
    p.add_argument("--fit", default=None, metavar="KEY,...", help="plant keys to fit (default: inertia, efficiency, "
                   "no-load torque, viscous, current-loop bandwidth; FRF only: inertia, current-loop bandwidth, with "
                   "--fidelity compliant also contact.stiffness_n_per_mm_e); drive.command_delay_s fits a continuous "
                   "command delay from --frf data")
    p.add_argument("--validate", nargs="+", default=[], metavar="CSV", help="records not fitted; their fit %% is reported")
    p.add_argument("--columns", default=None, metavar="name=header,...", help="map other CSV headers to the standard names")
    p.add_argument("--torque-constant", type=_number("--torque-constant"), metavar="N_M_PER_A",
                   help="torque constant for a current_a column, N m/A")
    p.add_argument("--load", type=_number("--load", positive=False), metavar="N", help="constant axial load, N, "
                   "for files without a load column")
    p.add_argument("--fidelity", default="rigid", choices=("rigid", "compliant"), help="model fidelity (default rigid)")
    p.add_argument("--segment", type=_number("--segment"), default=0.1, metavar="S",
                   help="multiple-shooting segment length, s (default 0.1)")
    p.add_argument("--delay-samples", type=int, default=0, metavar="N", help="samples between a logged command and "
                   "the sample it acts from (default 0)")
    p.add_argument("--design", choices=("multisine", "chirp", "steps"), help="write an excitation signal instead of fitting")
    p.add_argument("--duration", type=_number("--duration"), default=4.0, metavar="S", help="excitation length, s")
    p.add_argument("--sample-time", type=_number("--sample-time"), default=2.5e-4, metavar="S", help="sample time, s")
    p.add_argument("--f-min", type=_number("--f-min"), default=1.0, metavar="HZ", help="lowest frequency, Hz")
    p.add_argument("--f-max", type=_number("--f-max"), default=200.0, metavar="HZ", help="highest frequency, Hz")
    p.add_argument("--amplitude", type=_number("--amplitude"), default=20.0, metavar="A",
                   help="peak excursion (rad/s for a speed setpoint)")
    p.add_argument("--offset", type=_number("--offset", positive=False), default=30.0, metavar="A", help="mean value")
    return p


def _toml_string(text: str) -> str:
    return json.dumps(text, ensure_ascii=False)


def _toml_value(v) -> str:
    if isinstance(v, str):
        return _toml_string(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    return repr(float(v)) if isinstance(v, float) else repr(v)


def _uncertainty_line(key: str, entry) -> str:
    fields = ", ".join(f"{k} = {_toml_value(v)}" for k, v in entry.items())
    return f"{_toml_string(key)} = {{ {fields} }}"


def plant_toml(base_text: str, plant, name: str, keys: Sequence[str]) -> str:
    """The base plant file's text with the fitted keys' values, sources and uncertainty replaced.

    Parameters
    ----------
    base_text : str
        The base plant file (TOML), whose layout and comments are kept.
    plant : Plant
        The fitted plant (values, sources and ``uncertainty``: each fitted key's entry there
        replaces the base file's entry for that key in the ``[uncertainty]`` section, which is
        added at the end when the base file has none).
    name : str
        The new plant name.
    keys : sequence of str
        Plant keys to rewrite (``section.key``).
    """
    out, section, done = [], None, set()
    unc = dict(getattr(plant, "uncertainty", None) or {})
    new_unc = [k for k in keys if k in unc]
    unc_header = None
    for line in base_text.splitlines():
        m_sec = re.match(r"^\s*\[([A-Za-z_]+)\]\s*$", line)
        if m_sec:
            section = m_sec.group(1)
            if section == "uncertainty":
                unc_header = len(out)
        m_name = re.match(r"^name\s*=", line)
        if m_name and section is None:
            line = f"name = {_toml_string(name)}"
        if section == "uncertainty":
            m_unc = re.match(r'^\s*"?([A-Za-z0-9_.]+)"?\s*=', line)
            if m_unc and m_unc.group(1) in keys:
                continue  # replaced by the fit's entry below
        m_key = re.match(r"^(\s*)([A-Za-z0-9_]+)\s*=\s*\{.*\}\s*$", line)
        if m_key and section not in (None, "uncertainty") and f"{section}.{m_key.group(2)}" in keys:
            full = f"{section}.{m_key.group(2)}"
            line = (f"{m_key.group(1)}{m_key.group(2)} = {{ value = {plant.values[full]!r}, "
                    f"source = {_toml_string(plant.sources[full])} }}")
            done.add(full)
        out.append(line)
    missing = [k for k in keys if k not in done]
    if missing:
        raise PlantFileError(f"base plant file has no one-line entry for {', '.join(missing)}; expected "
                             "'key = { value = ..., source = \"...\" }' lines like the built-in plants")
    lines = [_uncertainty_line(k, unc[k]) for k in new_unc]
    if lines:
        if unc_header is None:
            out += ["", "# What the fit leaves uncertain (95 % intervals as truncated normals; prsa_ctrl.uncertainty)",
                    "[uncertainty]"]
            unc_header = len(out) - 1
        out[unc_header + 1:unc_header + 1] = lines
    return "\n".join(out) + "\n"


def _write_outputs(files: dict[str, tuple[str, str]], inputs: Sequence[str]) -> None:
    """The one place that writes files: ``{path: (flag, text)}``, each atomically."""
    from .output import write_text

    for path, (flag, text) in files.items():
        write_text(path, text, inputs=inputs, flag=flag)


def _check_outputs(paths: dict[str, str], inputs: Sequence[str]) -> None:
    from .output import check_writable

    for flag, path in paths.items():
        check_writable(path, inputs=inputs, flag=flag)


def _base_text(plant_arg: str | None) -> tuple[str, str | None]:
    """Text of the base plant file and its path (None for a built-in)."""
    from .plant import _resolve

    src = _resolve(plant_arg)
    return src.read_text(encoding="utf-8"), (str(src) if isinstance(src, Path) else None)


def _design(args) -> int:
    import numpy as np

    from .fitdata import design_excitation

    t, v = design_excitation(args.design, duration_s=args.duration, sample_time_s=args.sample_time,
                             f_min_hz=args.f_min, f_max_hz=args.f_max, amplitude=args.amplitude, offset=args.offset)
    _check_outputs({"--out": args.out}, [])
    lines = ["# prsa-fit --design " + args.design + ": speed setpoint (rad/s) for the drive's speed loop",
             "time_s,setpoint_rad_s"]
    lines += [f"{a:.9g},{b:.9g}" for a, b in zip(t, np.asarray(v))]
    _write_outputs({args.out: ("--out", "\n".join(lines) + "\n")}, [])
    print(f"wrote {args.out}: {args.design}, {len(t)} samples, {args.duration:g} s")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``prsa-fit``; returns the exit code."""
    from .fitdata import DataError, load_frf, load_record, parse_columns
    from .output import OutputError

    try:
        args = build_parser().parse_args(argv)
        if args.design:
            if args.data:
                raise _UsageError(f"--design with data files {' '.join(args.data)}; expected one or the other")
            return _design(args)
        if not args.data and not args.frf:
            raise _UsageError("no data file; expected prsa-fit DATA.csv [...] [--frf FRF.csv] --out PLANT.toml "
                              "(or --design)")
        if not 0 <= args.coherence_min < 1:
            raise _UsageError(f"--coherence-min {args.coherence_min!r}: expected 0 <= C < 1")
        from .fit import FITTABLE
        from .plant import load_plant

        keys = None
        if args.fit is not None:
            keys = [k.strip() for k in args.fit.split(",") if k.strip()]
            for k in keys:
                if k not in FITTABLE:
                    raise _UsageError(f"--fit {args.fit!r}: unknown key {k!r}; expected some of {', '.join(FITTABLE)}")
            if not keys:
                raise _UsageError(f"--fit {args.fit!r}: expected at least one key")
        if not 0 <= args.delay_samples <= 10:
            raise _UsageError(f"--delay-samples {args.delay_samples}: expected 0..10")
        plant = load_plant(args.plant)
        base_text, base_path = _base_text(args.plant)
        inputs = [*args.data, *args.validate, *args.frf] + ([base_path] if base_path else [])
        outs = {"--out": args.out}
        if args.json:
            outs["--json"] = args.json
        _check_outputs(outs, inputs)
        plot_paths = []
        if args.plots is not None:
            from .fit import figure_names
            from .output import check_directory

            check_directory(args.plots, "--plots")
            stems = figure_names([*(args.data or []), *(args.validate if args.data else [])], args.frf)
            plot_paths = [str(Path(args.plots) / f"{stem}.png") for stem in stems]
            _check_outputs({f"--plots {q}": q for q in plot_paths if Path(args.plots).is_dir()}, inputs)
        columns = parse_columns(args.columns) if args.columns else None
        opts = {"columns": columns, "torque_constant_n_m_per_a": args.torque_constant, "load_n": args.load}
        records = [load_record(f, **opts) for f in args.data]
        validate = [load_record(f, **opts) for f in args.validate]
        if args.validate and not args.data:
            raise _UsageError("--validate without DATA.csv; expected time-domain records to fit first")
        frf_load = args.frf_load if args.frf_load is not None else (args.load or 0.0)
        frfs = [load_frf(f, speed_rad_s=args.frf_speed, load_n=frf_load, coherence_min=args.coherence_min)
                for f in args.frf]
    except (_UsageError, argparse.ArgumentTypeError, DataError, PlantFileError, OutputError, ValueError) as exc:
        print(f"prsa-fit: error: {exc}", file=sys.stderr)
        return 2
    from .fit import FitError, fit_plant

    try:
        result = fit_plant(records, plant, frf=frfs, keys=keys, fidelity=args.fidelity, validate=validate,
                           segment_s=args.segment, delay_samples=args.delay_samples)
    except FitError as exc:
        print(f"prsa-fit: {exc}", file=sys.stderr)
        return 3
    except ValueError as exc:
        print(f"prsa-fit: error: {exc}", file=sys.stderr)
        return 2
    name = Path(args.out).stem
    text = plant_toml(base_text, result.plant, name, result.plant_keys)
    if result.delay is not None:  # not a plant-file key: said in a comment, reported in the JSON
        d, eq = result.delay, result.delay["equivalent_current_loop_bandwidth_hz"]
        text += (f"\n# prsa-fit: command delay {d['value']:.6g} s (95 % CI {d['ci95'][0]:.6g}..{d['ci95'][1]:.6g}, "
                 f"{d['samples']:.3g} samples) is not a plant-file key; a first-order current loop of "
                 f"{eq['value']:.6g} Hz has the same low-frequency phase lag\n")
    import tomllib

    from .plant import Plant

    Plant.from_dict(tomllib.loads(text), origin=args.out)  # what is written must load (with its [uncertainty])
    files = {args.out: ("--out", text)}
    if args.json:
        from .output import json_safe

        files[args.json] = ("--json", json.dumps(json_safe(result.report()), indent=2) + "\n")
    try:
        if args.plots is not None:
            plot_paths = _write_plots(result, args.plots, inputs)
        _write_outputs(files, inputs)
    except OutputError as exc:
        print(f"prsa-fit: error: {exc}", file=sys.stderr)
        return 2
    for k, v in result.parameters.items():
        lo, hi = v["ci95"]
        print(f"{k} = {v['value']:.6g} {v['unit']} (95 % CI {lo:.6g}..{hi:.6g})")
    if result.delay is not None:
        eq = result.delay["equivalent_current_loop_bandwidth_hz"]
        print(f"  (not written to the plant file: no delay key; equivalent current-loop bandwidth {eq['value']:.6g} Hz, "
              f"95 % CI {eq['ci95'][0]:.6g}..{eq['ci95'][1]:.6g})")
    j = result.reflected_inertia_kg_m2
    print(f"reflected inertia = {j['value']:.6g} kg m^2 (95 % CI {j['ci95'][0]:.6g}..{j['ci95'][1]:.6g})")
    for f, pct in result.fit_percent.items():
        print(f"fit {pct:.2f} % on {f}")
    for w in result.warnings:
        print(f"warning: {w}")
    print(f"wrote {args.out}" + (f" and {args.json}" if args.json else ""))
    if args.plots is not None:
        print("plots: " + ", ".join(plot_paths))
    return 0


def _write_plots(result, directory: str, inputs: Sequence[str]) -> list[str]:
    """Write :func:`prsa_ctrl.fit.fit_figures` as PNG files into ``directory`` (created if missing)."""
    import matplotlib.pyplot as plt

    from .fit import fit_figures
    from .output import make_directory, write_file

    make_directory(directory, "--plots")
    out = []
    for stem, fig in fit_figures(result).items():
        path = Path(directory) / f"{stem}.png"
        try:
            write_file(path, lambda tmp, fig=fig: fig.savefig(tmp, format="png", dpi=120), inputs, "--plots")
        finally:
            plt.close(fig)
        out.append(str(path))
    return out


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
