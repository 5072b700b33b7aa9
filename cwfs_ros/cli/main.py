"""The ``cwfs-ros`` command line: one argparse sub-command per task.

Usage::

    cwfs-ros estimate INTRA EXTRA --field-intra X Y --field-extra X Y [options]
    cwfs-ros --version

Adding a sub-command is one function: decorate ``_add_<name>(subparsers)`` with
:func:`subcommand`; it creates its parser and sets ``func`` (a callable taking the parsed
arguments and returning the exit status) with ``parser.set_defaults(func=...)``.  Heavy
imports (the core, matplotlib, rclpy) belong inside the handler, so that ``--help`` and
``--version`` stay fast and a sub-command never pays for another's dependencies.

Exit status (:data:`EXIT_CODES`, printed by ``--help``): 0 on success; 1 a check that
failed (``demo --check``) or a ROS tool whose node or topic is not there; 2 for bad input
or configuration (argparse's own usage errors, :class:`~cwfs_ros.errors.CwfsError`,
unreadable or unwritable files, a file that is not an image, a field outside the
instrument's field of view), each reported as one ``cwfs-ros <command>: error: <message>``
line on stderr without a traceback; 3 an estimate flagged unusable (caustic, implausible),
unless ``--allow-flagged``; 130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from cwfs_ros import __version__
from cwfs_ros.argtypes import finite_float as _finite_float
from cwfs_ros.argtypes import positive_int as _positive_int
from cwfs_ros.errors import CliError, CwfsError, ToolError
from cwfs_ros.runtime.memory import keep_freed_memory
from cwfs_ros.runtime.threads import limit_blas_threads

__all__ = ["main", "build_parser", "subcommand", "CliError"]

PROG = "cwfs-ros"
EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_FLAGGED = 3
EXIT_CODES = (
    (0, "success"),
    (EXIT_FAILED, "a check failed (demo --check), or a ROS tool found no such node or topic, "
                  "no message in time, a parameter the node refused, or a lifecycle transition "
                  "not available or refused"),
    (EXIT_USAGE, "bad input or configuration: usage, a missing or unreadable file, not an "
                 "image, a field outside the instrument's field of view, a bad parameter"),
    (EXIT_FLAGGED, "estimate/batch: an estimate flagged unusable (caustic, implausible); "
                   "--allow-flagged prints it and exits 0"),
    (130, "interrupted"),
)


def exit_codes_epilog() -> str:
    import textwrap

    return "exit status:\n" + "\n".join(
        textwrap.fill(t, 79, initial_indent=f"  {c:>3}  ", subsequent_indent=" " * 7)
        for c, t in EXIT_CODES)

# Registered sub-command builders, in the order they appear in ``--help``.
_SUBCOMMANDS: list[Callable[[Any], argparse.ArgumentParser]] = []


def subcommand(add: Callable[[Any], argparse.ArgumentParser]
               ) -> Callable[[Any], argparse.ArgumentParser]:
    """Register ``add(subparsers) -> parser`` as a sub-command builder (decorator)."""
    _SUBCOMMANDS.append(add)
    return add


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every registered sub-command."""
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Curvature wavefront sensing for Rubin/LSST (ROS 2 package cwfs_ros).",
        epilog=exit_codes_epilog(), formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for add in _SUBCOMMANDS:
        add(subparsers)
    return parser


def _error(command: str | None, message: str) -> int:
    name = f"{PROG} {command}" if command else PROG
    print(f"{name}: error: {message}", file=sys.stderr)
    return EXIT_USAGE


# Arguments that belong to ROS (rcl), not to a sub-command.
_ROS_FLAGS = ("-p", "--param", "-r", "--remap", "--params-file", "--log-level", "-e",
              "--enclave")


def _unrecognized(args: argparse.Namespace, extra: Sequence[str]) -> str:
    """The usage error for arguments no option takes, with the way to pass ROS arguments to
    a command that runs nodes (``-p NAME:=VALUE`` before ``--ros-args``)."""
    text = f"unrecognized arguments: {' '.join(extra)}"
    looks_ros = any(t in _ROS_FLAGS or ":=" in t for t in extra)
    if looks_ros and hasattr(args, "ros_args"):
        ros = " ".join(extra)
        text += (f"; ROS arguments go after --ros-args: {PROG} {args.command} --ros-args "
                 f"{ros}")
    return text


# A negative number as YAML writes it: argparse takes all but plain -1 and -0.5 for options.
_NEGATIVE = re.compile(r"-(\d[\d_]*\.?\d*|\.\d+)([eE][-+]?\d+)?|-\.(inf|Inf|INF)")


def _negative_values(argv: Sequence[str]) -> list[str]:
    """``param set NODE NAME -1e-3`` as argparse must read it: a negative VALUE (a number
    with an exponent, or -.inf) goes after ``--``, so that it is not taken for an option."""
    argv = list(argv)
    if argv[:2] != ["param", "set"] or "--" in argv:
        return argv
    neg = [i for i, a in enumerate(argv) if i >= 2 and _NEGATIVE.fullmatch(a)
           and argv[i - 1] != "--timeout"]
    if not neg:
        return argv
    return [a for i, a in enumerate(argv) if i not in neg] + ["--"] + [argv[i] for i in neg]


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (argparse exits are returned too)."""
    limit_blas_threads()
    keep_freed_memory()  # large messages reuse the heap's pages (runtime.memory)
    parser = build_parser()
    argv = _negative_values(sys.argv[1:] if argv is None else argv)
    try:
        args, extra = parser.parse_known_args(argv)
    except SystemExit as exc:  # --help, --version, usage errors (already printed)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    if extra:
        return _error(args.command, _unrecognized(args, extra))

    try:
        return int(args.func(args) or 0)
    except CliError as exc:
        return _error(args.command, str(exc))
    except BrokenPipeError:  # stdout closed early (e.g. piped into head): exit quietly
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 1
    except OSError as exc:
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        return _error(args.command, f"{where}{exc.strerror or exc}")
    except KeyboardInterrupt:
        print(f"{PROG} {args.command}: interrupted", file=sys.stderr)
        return 130
    except ToolError as exc:  # a graph tool's target is missing or refused the request
        _error(args.command, str(exc))
        return exc.exit_code
    except CwfsError as exc:  # the deliberate errors: bad image, configuration, bag, launch
        return _error(args.command, str(exc))



# -- estimate -----------------------------------------------------------------------------

SOLVER_CHOICES = ("exp", "fft", "lsq")
SOLVER_HELP = ("TIE (transport-of-intensity equation) solver: lsq (least squares; the "
               "smallest error under photon noise), or the paper's exp (series expansion) "
               "and fft (iterative FFT), kept to reproduce its figures (default: "
               "%(default)s)")


@subcommand
def _add_estimate(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "estimate",
        help="estimate Z4..Z22 from an intra/extra-focal donut pair",
        description=(
            "Estimate the wavefront (annular Zernikes Z4..Z22, nm of OPD) at the mid-point "
            "of the two stars' field positions from an intra- and an extra-focal donut "
            "image (.npy, FITS, or ZEMAX-style text). FITS files may carry the geometry in "
            "their header: FIELD_X, FIELD_Y (deg) and DEFOCUS (signed mm, negative intra); "
            "the command line wins. An estimate flagged unusable (caustic, or a departure "
            "from design the telescope cannot hold) is not printed: exit 3."
        ),
        epilog=exit_codes_epilog(), formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("intra", metavar="INTRA", help="intra-focal image file")
    p.add_argument("extra", metavar="EXTRA", help="extra-focal image file")
    p.add_argument("--field-intra", nargs=2, type=_finite_float,
                   metavar=("X", "Y"), help="field angle of the intra-focal star (deg; "
                                            "default: FIELD_X/FIELD_Y of its FITS header)")
    p.add_argument("--field-extra", nargs=2, type=_finite_float,
                   metavar=("X", "Y"), help="field angle of the extra-focal star (deg; "
                                            "default: FIELD_X/FIELD_Y of its FITS header)")
    p.add_argument("--defocal-offset", type=_finite_float, metavar="MM",
                   help="|detector offset| from focus in mm (default: |DEFOCUS| of the FITS "
                        "headers, else the instrument's)")
    p.add_argument("--instrument", default="lsst", metavar="NAME|PATH",
                   help="instrument name under config/instruments, or a YAML path "
                        "(default: %(default)s)")
    p.add_argument("--band", metavar="B",
                   help="optical band (default: the instrument's default band)")
    p.add_argument("--wavelength", type=_finite_float, metavar="NM",
                   help="wavelength in nm (default: the band's effective wavelength)")
    p.add_argument("--solver", choices=SOLVER_CHOICES, default="lsq",
                   help=SOLVER_HELP)
    p.add_argument("--allow-flagged", action="store_true",
                   help="print a flagged estimate (caustic, implausible) anyway, with its "
                        "flags, and exit 0")
    p.add_argument("--iterations", type=_positive_int, metavar="N",
                   help="outer iterations (default: config/algorithm.yaml)")
    p.add_argument("--seeing", type=_finite_float, default=0.0, metavar="ARCSEC",
                   help="seeing FWHM of the images: lsq and exp take the blur's edge signal out "
                        "(docs/accuracy.md, Seeing; default: none given)")
    p.add_argument("--json", action="store_true",
                   help="print the result as JSON (nothing else on stdout)")
    p.add_argument("--plot", metavar="PNG", type=Path,
                   help="write a diagnostic figure (donuts, Zernikes, convergence)")
    p.add_argument("--text-flip", action=argparse.BooleanOptionalAction, default=True,
                   help="flip text (ZEMAX) images vertically on reading (default: flip)")
    p.set_defaults(func=_run_estimate)
    return p


def _run_estimate(args: argparse.Namespace) -> int:
    from cwfs_ros.cli.provenance import format_geometry, run_pair

    if args.plot is not None and not args.plot.resolve().parent.is_dir():
        raise CliError(f"--plot {args.plot}: directory {args.plot.parent} does not exist")
    overrides: dict[str, Any] = {}
    if args.iterations is not None:
        overrides["outer_iterations"] = args.iterations
    run = run_pair(args.intra, args.extra, field_intra=args.field_intra,
                   field_extra=args.field_extra, instrument=args.instrument, band=args.band,
                   wavelength_nm=args.wavelength, defocal_offset_mm=args.defocal_offset,
                   solver=args.solver, seeing_fwhm_arcsec=args.seeing,
                   text_flip=args.text_flip, **overrides)
    result = run.result
    if run.flags and not args.allow_flagged:
        for c in run.flags:
            print(f"{PROG} estimate: flagged: {c.name}: {c.detail}", file=sys.stderr)
        print(f"{PROG} estimate: the estimate is not usable and is not printed "
              f"(--allow-flagged prints it); exit {EXIT_FLAGGED}", file=sys.stderr)
        return EXIT_FLAGGED
    if args.plot is not None:
        from cwfs_ros.cli.plotting import plot_result

        title = f"{Path(args.intra).name} / {Path(args.extra).name}"
        plot_result(result, args.plot, intra=run.inputs["intra"].image,
                    extra=run.inputs["extra"].image, title=title)
    if args.json:
        json.dump({**result.as_dict(), **run.record}, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(format_result(result))
        print(format_geometry(run.record))
        print(format_checks(run.checks))
        if args.plot is not None:
            print(f"plot: {args.plot}")
    return 0


@subcommand
def _add_demo(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "demo",
        help="run the closed active-optics loop on the simulated telescope (the main job)",
        description=(
            "Run the closed loop headless: camera_sim_node ray-traces the corner donuts of a "
            "perturbed LSST (batoid), wavefront_node estimates the wavefront, ofc_node "
            "computes the 50-DoF correction and the camera applies it, visit after visit "
            "(the graph of `cwfs-ros bringup --sim`, over real DDS inside this process). "
            "Writes a report (PNG, HTML, CSV, JSON) and prints where it is."
        ),
    )
    p.add_argument("--visits", type=_positive_int, default=8,
                   help="visits to run (default: %(default)s)")
    p.add_argument("--perturbation", choices=("rigid", "bending", "mixed"), default="rigid",
                   help="what is perturbed at the start, drawn within the strokes of "
                        "cwfs_ros.sim.perturbation.stroke_perturbation: the M2 and camera "
                        "hexapods (decentres up to 1 mm, tilts up to 30 arcsec, pistons up to "
                        "25 um), the mirrors' bending modes (up to 0.3 x range), or both; then "
                        "scaled to --wavefront-error (default: %(default)s)")
    p.add_argument("--wavefront-error", type=_finite_float, default=600.0, metavar="NM",
                   help="initial wavefront error, mean over corners of sqrt(sum Z4..Z22^2) "
                        "(default: %(default)s)")
    p.add_argument("--seed", type=int, default=1,
                   help="seed of the random perturbation (default: %(default)s)")
    p.add_argument("--photons", type=_finite_float, default=1e6,
                   help="photons per donut (default: %(default)g)")
    p.add_argument("--render-seed", type=int, default=7,
                   help="seed of the image noise and donut offsets (default: %(default)s)")
    p.add_argument("--seeing", type=_finite_float, default=0.0, metavar="ARCSEC",
                   help="atmospheric seeing (FWHM) of the simulated donuts, which the "
                        "estimator is told too, as by a seeing monitor (default: none)")
    p.add_argument("--params", action="append", default=[], metavar="FILE",
                   help="ROS parameter YAML overlaid on config/params.yaml and "
                        "config/sim.yaml (repeatable)")
    p.add_argument("--out", type=Path, default=Path("out") / "demo",
                   help="report directory (default: %(default)s)")
    p.add_argument("--visible", action="store_true",
                   help="let other processes on the DDS domain see the graph (e.g. to record "
                        "it with `cwfs-ros bag record`); off by default so that simulated "
                        "corrections never reach real actuators")
    p.add_argument("--domain-id", type=int, metavar="N",
                   help="DDS domain with --visible (default: ROS_DOMAIN_ID or 0)")
    p.add_argument("--rotator-angle", type=_finite_float, default=0.0, metavar="DEG",
                   help="camera rotator angle of every visit, -270..270 (default: "
                        "%(default)s)")
    p.add_argument("--check", action="store_true",
                   help="exit 1 unless the wavefront error over the science field falls at "
                        "least 5x within 5 visits (4 corrections) and every correction was "
                        "valid")
    p.add_argument("--verbose", action="store_true", help="show the nodes' INFO log")
    p.set_defaults(func=_run_demo)
    return p


def _run_demo(args: argparse.Namespace) -> int:
    """``cwfs-ros demo``: check the options, run the closed loop with a progress table, write
    the report; the exit status is the ``--check`` verdict (1 when it fails)."""
    from tqdm import tqdm

    from cwfs_ros.cli.demo import LoopConfig, LoopError, run_closed_loop, write_report
    from cwfs_ros.ros.launch import sim_params_file
    from cwfs_ros.sim.perturbation import stroke_perturbation

    _check_demo_args(args)
    args.out.mkdir(parents=True, exist_ok=True)
    dof = stroke_perturbation(args.perturbation, args.seed, args.wavefront_error)
    print(f"cwfs-ros demo: {args.perturbation} perturbation (seed {args.seed}) of "
          f"{args.wavefront_error:g} nm wavefront error, {args.visits} visits, "
          f"{args.photons:g} photons per donut"
          + (f", seeing {args.seeing:g} arcsec" if args.seeing > 0 else "")
          + (f", camera rotator {args.rotator_angle:g} deg" if args.rotator_angle else "")
          + ("" if args.visible else "; DDS discovery off (this process only)"), flush=True)
    # One override reaches both nodes that declare it: the camera renders that seeing and
    # the wavefront node is told it.
    seeing_args = ("-p", f"seeing_fwhm_arcsec:={args.seeing:g}") if args.seeing > 0 else ()
    config = LoopConfig(
        visits=args.visits, initial_dof=dof, n_photons=args.photons,
        render_seed=args.render_seed,
        params_files=[sim_params_file(), *args.params], visible=args.visible,
        domain_id=args.domain_id, rotator_angle_deg=args.rotator_angle,
        ros_args=(() if args.verbose else ("--log-level", "warn")) + seeing_args)
    # No bar in a log or a pipe: its redraws would be mixed into the table.
    bar = tqdm(total=args.visits, unit="visit", desc="closed loop", leave=False,
               disable=not sys.stderr.isatty())
    try:
        run = run_closed_loop(config, workdir=args.out, on_visit=_demo_visit_printer(bar),
                              on_status=lambda m: tqdm.write(m))
    except LoopError as exc:
        raise CliError(str(exc)) from None
    finally:
        bar.close()
    return _demo_summary(run, write_report(run, args.out), args.check)


def _check_demo_args(args: argparse.Namespace) -> None:
    """Refuse out-of-range demo options with a one-line error before anything starts."""
    from cwfs_ros.errors import ConfigError
    from cwfs_ros.wfs.blur import MAX_SEEING_FWHM_ARCSEC, check_seeing

    if not args.wavefront_error > 0:
        raise CliError(f"--wavefront-error must be > 0 nm, got {args.wavefront_error:g}")
    if not args.photons >= 1e3:
        raise CliError(f"--photons must be >= 1000, got {args.photons:g}")
    try:
        check_seeing(args.seeing)  # the estimator's own range check
    except ConfigError:
        raise CliError(f"--seeing must be in [0, {MAX_SEEING_FWHM_ARCSEC:g}] arcsec, got "
                       f"{args.seeing:g}") from None
    if args.domain_id is not None and not 0 <= args.domain_id <= 232:
        raise CliError(f"--domain-id must be in 0..232, got {args.domain_id}")
    if not -270.0 <= args.rotator_angle <= 270.0:
        raise CliError(f"--rotator-angle must be in [-270, 270] deg, got {args.rotator_angle:g}")
    for f in args.params:
        if not Path(f).is_file():
            raise CliError(f"--params {f}: no such file")


def _demo_visit_printer(bar: Any) -> Callable[[Any], None]:
    """The demo's ``on_visit``: one table row per visit (the header before the first),
    written above the progress ``bar``, which it advances."""
    from tqdm import tqdm

    header = (f"{'visit':>5}  {'true WFE':>9}  {'field WFE':>9}  {'FWHM':>8}  "
              f"{'measured':>9}  {'est. err':>8}  "
              f"{'correction':>10}  {'render':>7}  {'estimate':>8}  {'solve':>6}")

    def on_visit(r: Any) -> None:
        if r.visit == 1:
            tqdm.write(header + "\n" + f"{'':>5}  {'(nm)':>9}  {'(nm)':>9}  {'(arcsec)':>8}  "
                       f"{'(nm)':>9}  {'(nm rms)':>8}"
                       f"  {'':>10}  {'(s)':>7}  {'(ms)':>8}  {'(ms)':>6}")
        tqdm.write(f"{r.visit:>5}  {r.true_error_nm:>9.1f}  {r.field_error_nm:>9.1f}  "
                   f"{r.fwhm_arcsec:>8.3f}  {r.estimated_error_nm:>9.1f}  "
                   f"{r.median_estimate_error_nm:>8.1f}  "
                   f"{'valid' if r.correction_valid else 'REFUSED':>10}  {r.render_s:>7.1f}  "
                   f"{1e3 * r.estimate_s:>8.0f}  {1e3 * r.solve_s:>6.0f}")
        if not r.correction_valid:
            tqdm.write(f"       correction refused: {r.correction_status}")
        bar.update(1)
        bar.set_postfix_str(f"field WFE {r.field_error_nm:.0f} nm")

    return on_visit


def _demo_summary(run: Any, paths: dict[str, Path], check: bool) -> int:
    """Print the run's outcome and the report's paths; with ``check``, the verdict as the
    exit status (the field error down x5 within 5 visits, every correction valid)."""
    e, fe = run.true_error_nm, run.field_error_nm
    factor = run.reduction(5, "field")
    within = min(5, len(e))  # a shorter run is judged on the visits it has
    all_valid = all(r.correction_valid for r in run.records)
    print(f"wavefront error at the corners {e[0]:.0f} nm -> {e[-1]:.0f} nm, over the field "
          f"{fe[0]:.0f} nm -> {fe[-1]:.0f} nm in {len(e)} visits (field x{factor:.1f} within "
          f"{within} visits; start-up {run.startup_s:.1f} s, total {run.wall_s:.0f} s)")
    print(f"report: {paths['html'].resolve()}")
    print(f"figure: {paths['png'].resolve()}")
    if check:
        ok = factor >= 5.0 and all_valid
        print(f"check: {'PASS' if ok else 'FAIL'} (needs the field figure x5 within 5 "
              f"visits and every correction valid: x{factor:.1f} within {within}, "
              f"{sum(r.correction_valid for r in run.records)}/{len(run.records)} valid)")
        return 0 if ok else 1
    return 0


@subcommand
def _add_pair_demo(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "pair-demo",
        help="estimate the wavefront of one ray-traced, perturbed LSST pair against truth",
        description=(
            "Perturb the batoid LSST model (M2 and camera hexapods), ray-trace an intra/extra "
            "donut pair photon by photon with noise, estimate the wavefront, compare it with "
            "the model's true Zernikes, and write a figure."
        ),
    )
    p.add_argument("--out", type=Path, default=Path("out") / "pair_demo",
                   help="output directory (default: %(default)s)")
    p.add_argument("--field", nargs=2, type=_finite_float, default=(0.0, 0.0),
                   metavar=("X", "Y"), help="field angle in degrees (default: on axis)")
    p.add_argument("--photons", type=_finite_float, default=1e6,
                   help="photons per donut (default: %(default)g)")
    p.add_argument("--seed", type=int, default=1, help="random seed (default: %(default)s)")
    p.add_argument("--solver", choices=SOLVER_CHOICES, default="lsq", help=SOLVER_HELP)
    p.set_defaults(func=_run_pair_demo)
    return p


def _run_pair_demo(args: argparse.Namespace) -> int:
    import numpy as np

    from cwfs_ros.cli.pair_figure import plot_estimate_truth_design
    from cwfs_ros.cli.provenance import assess
    from cwfs_ros.errors import DonutCutError
    from cwfs_ros.sim.render import render_donut, true_zernikes_nm
    from cwfs_ros.sim.telescope import perturbed_telescope
    from cwfs_ros.wfs import estimate_wavefront, load_instrument

    args.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    dof = np.zeros(50)
    # M2 dz, dx, dy (um), rx, ry (deg); camera the same: a few hundred nm of wavefront.
    dof[:10] = rng.normal(0, 1, 10) * [10, 250, 250, 0.008, 0.008, 10, 250, 250, 0.008, 0.008]
    field = tuple(args.field)
    tel = perturbed_telescope(dof, band="r")
    truth = true_zernikes_nm(tel, field, wavelength_nm=622.0)
    print(f"perturbation: {format_hexapods(dof)}; wavefront "
          f"{np.sqrt(np.sum(truth**2)):.0f} nm (sqrt of the sum of Z4..Z22 squared)")
    print(f"ray-tracing intra and extra donuts ({args.photons:g} photons each) ...", flush=True)

    def render(centre: str) -> tuple[np.ndarray, np.ndarray]:
        return tuple(render_donut(tel, field, dz, wavelength_nm=622.0, npix=160,
                                  n_photons=args.photons, sky_per_pixel=50.0,
                                  subtract_sky=True, centre=centre, rng=rng)
                     for dz in (-1.5, 1.5))

    def estimate(intra: np.ndarray, extra: np.ndarray) -> Any:
        return estimate_wavefront(intra, extra, field_intra_deg=field, field_extra_deg=field,
                                  solver=args.solver)

    intra, extra = render("chief")
    try:
        result = estimate(intra, extra)
    except DonutCutError as exc:
        # Stamps are cut around the donut's light in a real pipeline; a large perturbation
        # moves the donut far from its chief ray, off the stamp centred there.
        print(f"{exc}: rendered again, each stamp centred on its donut's light", flush=True)
        intra, extra = render("centroid")
        result = estimate(intra, extra)
    print(format_result(result, table=False))
    print(format_checks(assess(result, load_instrument("lsst"), 1.5)))
    err = result.zernikes_nm - truth
    print(f"{'Noll':>4}  {'estimate':>9}  {'truth':>9}  {'error':>7}  {'design':>7}   (nm)")
    for j, e, t, d, i in zip(result.noll, result.zernikes_nm, truth, err,
                             result.intrinsic_nm, strict=True):
        print(f"{int(j):>4}  {e:>9.1f}  {t:>9.1f}  {d:>7.1f}  {i:>7.1f}")
    print(f"RMS error {np.sqrt(np.mean(err**2)):.1f} nm over Z4-Z22")
    png = plot_estimate_truth_design(
        result, truth, args.out / "demo_estimate.png", intra=intra, extra=extra,
        title=f"ray-traced, perturbed LSST pair (batoid) at field ({field[0]:g}, "
              f"{field[1]:g}) deg, {args.photons:g} photons per donut\n{format_hexapods(dof)}")
    np.savez(args.out / "demo_pair.npz", intra=intra, extra=extra, truth_nm=truth, dof=dof)
    # The images alone, as `estimate` reads them: the way to "your own data".
    for name, img in (("intra", intra), ("extra", extra)):
        np.save(args.out / f"{name}.npy", img)
    print(f"report: {png.resolve()}")
    print(f"the same pair again: cwfs-ros estimate {args.out / 'intra.npy'} "
          f"{args.out / 'extra.npy'} --field-intra {field[0]:g} {field[1]:g} "
          f"--field-extra {field[0]:g} {field[1]:g}")
    return 0


def format_hexapods(dof: Any) -> str:
    """The M2 and camera hexapod DoF (0-9 of the 50) with their units."""
    def one(v: Any) -> str:
        return (f"dz {v[0]:+.2f} um, dx {v[1]:+.1f} um, dy {v[2]:+.1f} um, "
                f"rx {v[3]:+.4f} deg, ry {v[4]:+.4f} deg")

    return f"M2 {one(dof[:5])}; camera {one(dof[5:10])}"


def _register_ros_subcommands() -> None:
    # bringup / node live with the launch code (light import: stdlib + cwfs_ros.config).
    from cwfs_ros.ros.launch import add_bringup_parser, add_node_parser

    subcommand(add_bringup_parser)
    subcommand(add_node_parser)


_register_ros_subcommands()


def _register_bag_subcommands() -> None:
    # bag record|play|info and replay (light imports: stdlib only until a handler runs).
    from functools import partial

    from cwfs_ros.cli.replay import add_replay_parser
    from cwfs_ros.ros.bag import add_bag_parser

    subcommand(partial(add_bag_parser, cli_error=CliError))
    subcommand(partial(add_replay_parser, cli_error=CliError))


_register_bag_subcommands()


def _register_validate_subcommand() -> None:
    # validate: the paper's Figs. 4-10 and beyond (stdlib only until the handler runs).
    from functools import partial

    from cwfs_ros.cli.validate import add_validate_parser

    subcommand(partial(add_validate_parser, cli_error=CliError))


_register_validate_subcommand()


def _register_rostools_subcommands() -> None:
    # topic list|echo|hz, param list|get|set|dump and lifecycle get|set|list (`node list`
    # is on the node parser).
    from cwfs_ros.ros.tools import add_lifecycle_parser, add_param_parser, add_topic_parser

    subcommand(add_topic_parser)
    subcommand(add_param_parser)
    subcommand(add_lifecycle_parser)


_register_rostools_subcommands()


def _register_batch_subcommand() -> None:
    from functools import partial

    from cwfs_ros.cli.batch import add_batch_parser

    subcommand(partial(add_batch_parser, cli_error=CliError, solver_help=SOLVER_HELP,
                       epilog=exit_codes_epilog()))


_register_batch_subcommand()


def format_result(result: Any, *, table: bool = True) -> str:
    """Human-readable table of Z4..Z22 (unless ``table`` is False) plus a status line."""
    lines = [
        f"instrument {result.instrument}, band {result.band} ({result.wavelength_nm:g} nm), "
        f"solver {result.solver}, field ({result.field_deg[0]:.4f}, "
        f"{result.field_deg[1]:.4f}) deg",
    ]
    if table:
        lines.append(f"{'Noll':>4}  {'Z (nm)':>10}  {'design (nm)':>11}")
        for j, z, d in zip(result.noll, result.zernikes_nm, result.intrinsic_nm, strict=True):
            lines.append(f"{int(j):>4}  {z:>10.2f}  {d:>11.2f}")
    # "settled": the last update fell below the solver's tolerance. It is not a verdict on
    # accuracy (an unsettled estimate ran out of iterations while still moving slightly).
    lines.append(
        f"caustic: {'yes' if result.caustic else 'no'}, "
        f"settled: {'yes' if result.converged else 'no'}, "
        f"iterations: {result.iterations}, swap check: {result.swap_check}, "
        f"wall time: {result.wall_time_s:.3f} s"
    )
    return "\n".join(lines)


def format_checks(checks: Sequence[Any]) -> str:
    """One line per check of :func:`cwfs_ros.cli.provenance.assess`."""
    return "\n".join(f"check {c.name}: {c.outcome} ({c.detail})" for c in checks)


if __name__ == "__main__":
    raise SystemExit(main())
