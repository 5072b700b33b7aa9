"""The ``cwfs-ros`` command line: one argparse sub-command per task.

Usage::

    cwfs-ros estimate INTRA EXTRA --field-intra X Y --field-extra X Y [options]
    cwfs-ros --version

Adding a sub-command is one function: decorate ``_add_<name>(subparsers)`` with
:func:`subcommand`; it creates its parser and sets ``func`` (a callable taking the parsed
arguments and returning the exit status) with ``parser.set_defaults(func=...)``.  Heavy
imports (the core, matplotlib, rclpy) belong inside the handler, so that ``--help`` and
``--version`` stay fast and a sub-command never pays for another's dependencies.

Exit status: 0 on success, 2 for bad input or configuration (argparse's own usage errors,
:class:`~cwfs_ros.core.errors.CwfsError`, unreadable or unwritable files), each reported as
one ``cwfs-ros <command>: error: <message>`` line on stderr without a traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from . import __version__

__all__ = ["main", "build_parser", "subcommand", "CliError"]

PROG = "cwfs-ros"
EXIT_USAGE = 2

# Registered sub-command builders, in the order they appear in ``--help``.
_SUBCOMMANDS: list[Callable[[Any], argparse.ArgumentParser]] = []


class CliError(Exception):
    """A user-facing error of a sub-command: reported on stderr, exit status 2."""


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


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (argparse exits are returned too)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, usage errors (already printed)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)

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
    except Exception as exc:
        # The core's deliberate errors (bad image, bad configuration). Looked up only if the
        # handler imported the core, so sub-commands that do not need it never load it.
        errors = sys.modules.get("cwfs_ros.core.errors")
        if errors is not None and isinstance(exc, errors.CwfsError):
            return _error(args.command, str(exc))
        raise


# -- shared argument types ----------------------------------------------------------------

def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {value}")
    return value


def _finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


# -- estimate -----------------------------------------------------------------------------

SOLVER_CHOICES = ("exp", "fft", "lsq")


@subcommand
def _add_estimate(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "estimate",
        help="estimate Z4..Z22 from an intra/extra-focal donut pair",
        description=(
            "Estimate the wavefront (annular Zernikes Z4..Z22, nm of OPD) at the mid-point "
            "of the two stars' field positions from an intra- and an extra-focal donut "
            "image (.npy, FITS, or ZEMAX-style text)."
        ),
    )
    p.add_argument("intra", metavar="INTRA", help="intra-focal image file")
    p.add_argument("extra", metavar="EXTRA", help="extra-focal image file")
    p.add_argument("--field-intra", nargs=2, type=_finite_float, required=True,
                   metavar=("X", "Y"), help="field angle of the intra-focal star (deg)")
    p.add_argument("--field-extra", nargs=2, type=_finite_float, required=True,
                   metavar=("X", "Y"), help="field angle of the extra-focal star (deg)")
    p.add_argument("--defocal-offset", type=_finite_float, metavar="MM",
                   help="|detector offset| from focus in mm (default: the instrument's)")
    p.add_argument("--instrument", default="lsst", metavar="NAME|PATH",
                   help="instrument name under config/instruments, or a YAML path "
                        "(default: %(default)s)")
    p.add_argument("--band", metavar="B",
                   help="optical band (default: the instrument's default band)")
    p.add_argument("--wavelength", type=_finite_float, metavar="NM",
                   help="wavelength in nm (default: the band's effective wavelength)")
    p.add_argument("--solver", choices=SOLVER_CHOICES, default="exp",
                   help="TIE solver (default: %(default)s)")
    p.add_argument("--iterations", type=_positive_int, metavar="N",
                   help="outer iterations (default: config/algorithm.yaml)")
    p.add_argument("--json", action="store_true",
                   help="print the result as JSON (nothing else on stdout)")
    p.add_argument("--plot", metavar="PNG", type=Path,
                   help="write a diagnostic figure (donuts, Zernikes, convergence)")
    p.add_argument("--text-flip", action=argparse.BooleanOptionalAction, default=True,
                   help="flip text (ZEMAX) images vertically on reading (default: flip)")
    p.set_defaults(func=_run_estimate)
    return p


def _read(path: str, role: str, text_flip: bool) -> Any:
    from .core.io import read_image

    p = Path(path)
    if not p.exists():
        raise CliError(f"{role} image {path}: no such file")
    if not p.is_file():
        raise CliError(f"{role} image {path}: not a regular file")
    return read_image(path, text_flip=text_flip)


def _run_estimate(args: argparse.Namespace) -> int:
    from .core import estimate_wavefront, load_instrument

    if args.plot is not None and not args.plot.resolve().parent.is_dir():
        raise CliError(f"--plot {args.plot}: directory {args.plot.parent} does not exist")
    inst = load_instrument(args.instrument)
    intra = _read(args.intra, "intra", args.text_flip)
    extra = _read(args.extra, "extra", args.text_flip)
    overrides: dict[str, Any] = {}
    if args.iterations is not None:
        overrides["outer_iterations"] = args.iterations
    result = estimate_wavefront(
        intra, extra,
        field_intra_deg=tuple(args.field_intra), field_extra_deg=tuple(args.field_extra),
        instrument=inst, band=args.band or inst.default_band, wavelength_nm=args.wavelength,
        defocal_offset_mm=args.defocal_offset, solver=args.solver, **overrides,
    )
    if args.plot is not None:
        from .plotting import plot_result

        title = f"{Path(args.intra).name} / {Path(args.extra).name}"
        plot_result(result, args.plot, intra=intra, extra=extra, title=title)
    if args.json:
        json.dump(result.as_dict(), sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(format_result(result))
        if args.plot is not None:
            print(f"plot: {args.plot}")
    return 0


@subcommand
def _add_demo(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "demo",
        help="estimate the wavefront of a ray-traced, perturbed LSST and compare with truth",
        description=(
            "Perturb the batoid LSST model (M2 and camera hexapods), ray-trace an intra/extra "
            "donut pair photon by photon with noise, estimate the wavefront, compare it with "
            "the model's true Zernikes, and write a figure."
        ),
    )
    p.add_argument("--out", type=Path, default=Path("out") / "demo",
                   help="output directory (default: %(default)s)")
    p.add_argument("--field", nargs=2, type=_finite_float, default=(0.0, 0.0),
                   metavar=("X", "Y"), help="field angle in degrees (default: on axis)")
    p.add_argument("--photons", type=_finite_float, default=1e6,
                   help="photons per donut (default: %(default)g)")
    p.add_argument("--seed", type=int, default=1, help="random seed (default: %(default)s)")
    p.add_argument("--solver", choices=SOLVER_CHOICES, default="exp",
                   help="TIE solver (default: %(default)s)")
    p.set_defaults(func=_run_demo)
    return p


def _run_demo(args: argparse.Namespace) -> int:
    import numpy as np

    from .core import estimate_wavefront
    from .plotting import plot_result
    from .sim.render import render_donut, true_zernikes_nm
    from .sim.telescope import perturbed_telescope

    args.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    dof = np.zeros(50)
    # M2 dz, dx, dy (um), rx, ry (deg); camera the same: a few hundred nm of wavefront.
    dof[:10] = rng.normal(0, 1, 10) * [10, 250, 250, 0.008, 0.008, 10, 250, 250, 0.008, 0.008]
    field = tuple(args.field)
    tel = perturbed_telescope(dof, band="r")
    truth = true_zernikes_nm(tel, field, wavelength_nm=622.0)
    print(f"perturbation: M2 {np.round(dof[:5], 3).tolist()}, camera "
          f"{np.round(dof[5:10], 3).tolist()}; wavefront {np.sqrt(np.sum(truth**2)):.0f} nm")
    print(f"ray-tracing intra and extra donuts ({args.photons:g} photons each) ...", flush=True)
    intra, extra = (render_donut(tel, field, dz, wavelength_nm=622.0, npix=160,
                                 n_photons=args.photons, sky_per_pixel=50.0,
                                 subtract_sky=True, rng=rng) for dz in (-1.5, 1.5))
    result = estimate_wavefront(intra, extra, field_intra_deg=field, field_extra_deg=field,
                                solver=args.solver)
    print(format_result(result))
    err = result.zernikes_nm - truth
    print(f"{'Noll':>4}  {'estimate':>9}  {'truth':>9}  {'error':>7}   (nm)")
    for j, e, t, d in zip(result.noll, result.zernikes_nm, truth, err, strict=True):
        print(f"{int(j):>4}  {e:>9.1f}  {t:>9.1f}  {d:>7.1f}")
    print(f"RMS error {np.sqrt(np.mean(err**2)):.1f} nm over Z4-Z22")
    png = plot_result(result, args.out / "demo_estimate.png", intra=intra, extra=extra,
                      title="ray-traced LSST pair (batoid), estimate vs truth")
    np.savez(args.out / "demo_pair.npz", intra=intra, extra=extra, truth_nm=truth, dof=dof)
    print(f"report: {png.resolve()}")
    return 0


def _register_ros_subcommands() -> None:
    # bringup / node live with the launch code (light import: stdlib + cwfs_ros.paths).
    from .launch import add_bringup_parser, add_node_parser

    subcommand(add_bringup_parser)
    subcommand(add_node_parser)


_register_ros_subcommands()


def format_result(result: Any) -> str:
    """Human-readable table of Z4..Z22 plus a status line."""
    lines = [
        f"instrument {result.instrument}, band {result.band} ({result.wavelength_nm:g} nm), "
        f"solver {result.solver}, field ({result.field_deg[0]:.4f}, "
        f"{result.field_deg[1]:.4f}) deg",
        f"{'Noll':>4}  {'Z (nm)':>10}  {'design (nm)':>11}",
    ]
    for j, z, d in zip(result.noll, result.zernikes_nm, result.intrinsic_nm, strict=True):
        lines.append(f"{int(j):>4}  {z:>10.2f}  {d:>11.2f}")
    lines.append(
        f"caustic: {'yes' if result.caustic else 'no'}, "
        f"converged: {'yes' if result.converged else 'no'}, "
        f"iterations: {result.iterations}, wall time: {result.wall_time_s:.3f} s"
    )
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
