"""``cwfs-ros batch``: estimate every pair of a table and write a table of results.

Input: a CSV or ECSV table (astropy reads either), one pair per row.  Columns:

=====================  ===============================================================
``intra``, ``extra``   image files (relative paths are relative to the table's folder)
``field_intra_x/_y``   field of the intra-focal star (deg); optional with FITS headers
``field_extra_x/_y``   field of the extra-focal star (deg); optional with FITS headers
``defocal_offset_mm``  optional: |detector offset| (default: FITS header, else instrument)
=====================  ===============================================================

Output (``--out``; ECSV when it ends in ``.ecsv``, else CSV): the input columns, then
``status`` (ok / flagged / error), ``flags``, ``error``, the instrument, band, wavelength,
solver and defocus used, the field of the estimate, ``Z4_nm`` ... ``Z22_nm``, ``caustic``,
``settled``, ``last_update_nm`` (the outer loop's last update), ``swap_check``,
``iterations`` and ``warnings`` (the checks whose outcome is a WARNING, such as ``settled``
when the loop was still moving by more than 1 nm).  A flagged row's Zernikes are NaN unless
``--allow-flagged``.  The ECSV header carries the software versions and the options.

Exit status: 0 every row estimated and none flagged; 2 some row could not be estimated (its
``error`` says why; the other rows are still written); 3 some row flagged (not with
``--allow-flagged``).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from cwfs_ros.argtypes import finite_float
from cwfs_ros.errors import ConfigError
from cwfs_ros.layout import NOLL

__all__ = ["add_batch_parser", "read_pairs", "run_batch"]

_OPTIONAL = ("field_intra_x", "field_intra_y", "field_extra_x", "field_extra_y",
             "defocal_offset_mm")


def read_pairs(path: Path) -> Any:
    """The table of pairs (astropy Table), its required columns checked."""
    from astropy.table import Table

    from cwfs_ros.errors import ConfigError

    fmt = "ascii.ecsv" if path.suffix.lower() == ".ecsv" else "ascii.csv"
    try:
        table = Table.read(path, format=fmt)
    except Exception as exc:  # noqa: BLE001 - astropy raises many kinds for a bad table
        raise ConfigError(f"table {path}: cannot read it as {fmt}: {exc}") from None
    missing = [c for c in ("intra", "extra") if c not in table.colnames]
    if missing:
        raise ConfigError(f"table {path}: missing column(s) {missing}; needs intra, extra "
                          f"and optionally {', '.join(_OPTIONAL)}")
    return table


def _column_hints(colnames: list[str]) -> list[str]:
    """For each column that is none of the table's own but nearly one that is missing (a
    misspelling, read as a column of the user's and kept as such): the name it looks like."""
    from difflib import get_close_matches

    known = ("intra", "extra", *_OPTIONAL)
    absent = [k for k in known if k not in colnames]
    out = []
    for c in colnames:
        if c in known:
            continue
        near = get_close_matches(c.lower(), absent, n=1, cutoff=0.75)
        if near:
            out.append(f"batch: column {c!r} is not read (did you mean {near[0]!r}?)")
    return out


def _value(row: Any, name: str) -> float | None:
    if name not in row.colnames:
        return None
    v = row[name]
    if getattr(v, "mask", False) is True or v is None or str(v).strip() in ("", "--"):
        return None
    try:
        out = float(v)
    except (TypeError, ValueError):
        raise ConfigError(f"column {name}: {str(v)!r} is not a number") from None
    if not math.isfinite(out):
        raise ConfigError(f"column {name}: {str(v)!r} is not a finite number")
    return out


def _pair_args(row: Any, base: Path) -> dict[str, Any]:
    def path(name: str) -> Path:
        p = Path(str(row[name]))
        return p if p.is_absolute() else base / p

    fi = [_value(row, f"field_intra_{a}") for a in "xy"]
    fe = [_value(row, f"field_extra_{a}") for a in "xy"]
    return {"intra": path("intra"), "extra": path("extra"),
            "field_intra": None if None in fi else fi, "field_extra": None if None in fe else fe,
            "defocal_offset_mm": _value(row, "defocal_offset_mm")}


def _row_out(run: Any, allow_flagged: bool) -> dict[str, Any]:
    r = run.result
    flagged = bool(run.flags)
    hide = flagged and not allow_flagged
    out: dict[str, Any] = {
        "status": "flagged" if flagged else "ok",
        "flags": " ".join(c.name for c in run.flags), "error": "",
        "instrument": r.instrument, "band": r.band, "wavelength_nm": r.wavelength_nm,
        "solver": r.solver, "defocal_offset_used_mm": run.record["defocal_offset_mm"],
        "field_x_deg": r.field_deg[0], "field_y_deg": r.field_deg[1]}
    for j, z in zip(NOLL, r.zernikes_nm, strict=True):
        out[f"Z{j}_nm"] = float("nan") if hide else float(z)
    from cwfs_ros.cli.provenance import last_update_nm

    out.update(caustic=bool(r.caustic), settled=bool(r.converged), last_update_nm=last_update_nm(r),
               swap_check=r.swap_check, iterations=int(r.iterations),
               warnings=" ".join(c.name for c in run.checks if c.warning))
    return out


def _error_row(message: str) -> dict[str, Any]:
    import numpy as np

    out: dict[str, Any] = {"status": "error", "flags": "", "error": message,
                           "instrument": "", "band": "", "wavelength_nm": float("nan"),
                           "solver": "", "defocal_offset_used_mm": float("nan"),
                           "field_x_deg": float("nan"), "field_y_deg": float("nan")}
    out.update({f"Z{j}_nm": float("nan") for j in NOLL})
    # Not estimated: these are empty cells (masked), not a caustic-free unsettled estimate.
    out.update(caustic=np.ma.masked, settled=np.ma.masked, last_update_nm=float("nan"),
               swap_check="", iterations=np.ma.masked, warnings="")
    return out


def run_batch(table_path: Path, out_path: Path, options: dict[str, Any],
              allow_flagged: bool = False, say: Any = print) -> tuple[Any, dict[str, int]]:
    """Estimate every row; write ``out_path``; the table written and the counts."""
    from astropy import units as u
    from astropy.table import Table

    from cwfs_ros.cli.provenance import run_pair, software_versions
    from cwfs_ros.errors import CwfsError

    pairs = read_pairs(table_path)
    for hint in _column_hints(pairs.colnames):
        say(hint)
    rows = []
    for k, row in enumerate(pairs):
        try:
            run = run_pair(**_pair_args(row, table_path.parent), **options)
            rows.append(_row_out(run, allow_flagged))
        except CwfsError as exc:
            rows.append(_error_row(str(exc)))
        say(f"{k + 1}/{len(pairs)} {row['intra']}: {rows[-1]['status']}"
            + (f" ({rows[-1]['flags'] or rows[-1]['error']})"
               if rows[-1]["status"] != "ok" else ""))
    res = Table(rows=rows, names=list(rows[0]) if rows else None)
    out = pairs.copy()
    for name in res.colnames:
        out[name] = res[name]
    for name in out.colnames:
        if name.endswith("_nm"):
            out[name].unit = u.nm
        elif name.endswith("_deg") or name.startswith("field_"):
            out[name].unit = u.deg
        elif name.endswith("_mm"):
            out[name].unit = u.mm
    out.meta.update(software=software_versions(), options=dict(options),
                    table=str(table_path))
    fmt = "ascii.ecsv" if out_path.suffix.lower() == ".ecsv" else "ascii.csv"
    out.write(out_path, format=fmt, overwrite=True)
    counts = {s: sum(r["status"] == s for r in rows) for s in ("ok", "flagged", "error")}
    return out, counts


def add_batch_parser(subparsers: Any, *, cli_error: type[Exception],
                     solver_help: str, epilog: str) -> argparse.ArgumentParser:
    """Register ``batch`` (sets ``func``)."""
    p = subparsers.add_parser(
        "batch", help="estimate every pair of a CSV/ECSV table; write a table of results",
        description=__doc__.split("\n\n", 1)[1].split("Exit status")[0],
        epilog=epilog, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("table", type=Path, metavar="TABLE", help="CSV or ECSV table of pairs")
    p.add_argument("--out", type=Path, required=True, metavar="FILE",
                   help="results table (.ecsv: ECSV with units and provenance; else CSV)")
    p.add_argument("--instrument", default="lsst", metavar="NAME|PATH",
                   help="instrument (default: %(default)s)")
    p.add_argument("--band", metavar="B", help="band (default: the instrument's)")
    p.add_argument("--wavelength", type=finite_float, metavar="NM",
                   help="wavelength in nm (default: the band's)")
    p.add_argument("--solver", choices=("exp", "fft", "lsq"), default="lsq", help=solver_help)
    p.add_argument("--seeing", type=finite_float, default=0.0, metavar="ARCSEC",
                   help="seeing FWHM of the images (default: none given)")
    p.add_argument("--text-flip", action=argparse.BooleanOptionalAction, default=True,
                   help="flip text (ZEMAX) images vertically on reading (default: flip)")
    p.add_argument("--allow-flagged", action="store_true",
                   help="write the Zernikes of flagged rows too, and exit 0 for them")
    p.set_defaults(func=lambda args: _run(args, cli_error))
    return p


def _run(args: argparse.Namespace, cli_error: type[Exception]) -> int:
    if not args.table.is_file():
        raise cli_error(f"table {args.table}: no such file")
    if not args.out.resolve().parent.is_dir():
        raise cli_error(f"--out {args.out}: directory {args.out.parent} does not exist")
    options = {"instrument": args.instrument, "band": args.band,
               "wavelength_nm": args.wavelength, "solver": args.solver,
               "seeing_fwhm_arcsec": args.seeing, "text_flip": args.text_flip}
    _, counts = run_batch(args.table, args.out, options, args.allow_flagged,
                          say=lambda m: print(m, file=sys.stderr, flush=True))
    print(f"batch: {sum(counts.values())} pairs: {counts['ok']} ok, {counts['flagged']} "
          f"flagged, {counts['error']} errors -> {args.out}")
    if counts["error"]:
        return 2
    return 3 if counts["flagged"] and not args.allow_flagged else 0
