"""Reading donut images from files: NumPy ``.npy``, FITS and whitespace-separated text.

Text images are those of the ZEMAX reference set (bxin/cwfs): one row per line, stored with
row 0 at the top of the picture.  The reference code flips them vertically on reading; after
that flip they are in the focal-plane frame ``[row=y, col=x]`` used throughout this package
(checked by forward-modelling all eight re-orientations of the FAM set; see
docs/cli.md), so :func:`read_image` applies the same flip to ``.txt`` files.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from cwfs_ros.errors import ImageError

__all__ = ["read_image"]


def _plain(exc: Exception) -> str:
    """The reading error in the terms of an image: numpy's advice for a ragged table
    (``usecols``) is about tables, not images."""
    text = str(exc)
    m = re.match(r"the number of columns changed from (\d+) to (\d+) at row (\d+)", text)
    if m:
        return (f"its rows differ in length: row {m.group(3)} has {m.group(2)} values, the "
                f"rows before it {m.group(1)}")
    return text


def read_image(path: str | Path, *, text_flip: bool = True) -> np.ndarray:
    """Read a 2-D image as float64 ``[row=y, col=x]``.

    Args:
        path: ``.npy``, ``.fits``/``.fit``/``.fits.gz`` (first HDU with 2-D data) or text.
        text_flip: flip text images vertically (the ZEMAX set's storage order).

    Raises:
        ImageError: unreadable file or not a 2-D numeric image.
    """
    p = Path(path)
    name = p.name.lower()
    try:
        if name.endswith(".npy"):
            data = np.load(p, allow_pickle=False)
        elif name.endswith((".fits", ".fit", ".fits.gz", ".fz")):
            from astropy.io import fits

            with fits.open(p) as hdul:
                data = next((h.data for h in hdul if h.data is not None and h.data.ndim == 2),
                            None)
                if data is None:
                    raise ImageError(f"{p}: no 2-D image HDU")
                data = np.array(data, dtype=np.float64)
        else:
            data = np.loadtxt(p, dtype=np.float64, ndmin=2)
            if text_flip:
                data = data[::-1, :]
    except ImageError:
        raise
    except (OSError, ValueError) as exc:
        raise ImageError(f"cannot read image {p}: {_plain(exc)}") from exc
    data = np.asarray(data)
    if data.ndim != 2 or not np.issubdtype(data.dtype, np.number):
        raise ImageError(f"{p}: expected a 2-D numeric image, got shape {data.shape} "
                         f"dtype {data.dtype}")
    return np.ascontiguousarray(data, dtype=np.float64)
