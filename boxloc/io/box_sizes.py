"""The carton list of a depalletizing cell: ``--box-sizes FILE``.

The file is a CSV with the header ``width,length,height`` and one row per carton size
(SKU), metres. ``height`` may be empty (unknown). ``width`` and ``length`` may come in
either order; they are normalised to ``width <= length``, as :class:`boxloc.config.Config`
keeps them. Every problem raises :class:`boxloc.errors.InputError` with one line naming
the file, the row and the problem.

Example::

    width,length,height
    0.30,0.40,0.25
    0.20,0.30,
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from boxloc.errors import InputError

#: The header the file must start with, exactly.
HEADER = ("width", "length", "height")

#: A carton list longer than this is not a list of cartons (and would make every test of a
#: rectangle's size against it slow): refused.
MAX_SIZES = 10_000

#: Files larger than this are refused before they are read, bytes.
MAX_BYTES = 4 * 1024 * 1024


def read_box_sizes(path: str | Path) -> tuple[tuple[float, float, float], ...]:
    """Read a carton list.

    Parameters
    ----------
    path : str or Path
        A CSV file: header ``width,length,height``, then one row per carton size, metres;
        ``height`` may be empty.

    Returns
    -------
    tuple of (width, length, height) float tuples
        Metres, ``width <= length``, ``height`` NaN where the file leaves it empty; in the
        file's order (row i is ``Config.box_sizes[i]``, the ``sku`` the results name).

    Raises
    ------
    InputError
        Missing or unreadable file, a header other than ``width,length,height``, a row
        with another number of fields, a value that is not a number, not finite or not
        positive, or no rows at all.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"box sizes file not found: {p}")
    try:
        if p.stat().st_size > MAX_BYTES:
            raise InputError(f"{p}: box sizes file larger than {MAX_BYTES} bytes")
        text = p.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(f"{p}: box sizes file is not UTF-8 text") from None
    except OSError as e:
        raise InputError(f"{p}: cannot read box sizes file ({e.strerror})") from None
    try:
        rows = list(csv.reader(io.StringIO(text)))
    except csv.Error as e:
        raise InputError(f"{p}: not a CSV file ({e})") from None
    if not rows:
        raise InputError(f"{p}: empty file, expected the header width,length,height")
    header = tuple(c.strip().lower() for c in rows[0])
    if header != HEADER:
        raise InputError(f"{p}: row 1: header must be width,length,height, got "
                         f"{','.join(rows[0])[:80]!r}")
    out: list[tuple[float, float, float]] = []
    for line, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue  # blank lines
        if len(row) != 3:
            raise InputError(f"{p}: row {line}: expected 3 fields (width,length,height), "
                             f"got {len(row)}")
        vals = []
        for name, cell in zip(HEADER, row):
            cell = cell.strip()
            if name == "height" and not cell:
                vals.append(math.nan)
                continue
            try:
                v = float(cell)
            except ValueError:
                raise InputError(f"{p}: row {line}: {name} is not a number: "
                                 f"{cell[:40]!r}") from None
            if not math.isfinite(v) or v <= 0:
                raise InputError(f"{p}: row {line}: {name} must be a positive finite "
                                 f"length in metres, got {cell[:40]}")
            vals.append(v)
        if len(out) >= MAX_SIZES:
            raise InputError(f"{p}: row {line}: more than {MAX_SIZES} carton sizes")
        w, ln = sorted(vals[:2])
        out.append((w, ln, vals[2]))
    if not out:
        raise InputError(f"{p}: no carton sizes after the header")
    return tuple(out)
