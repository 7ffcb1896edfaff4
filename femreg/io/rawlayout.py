"""How the samples of a headerless (raw) RF file are laid out, told by the RF carrier and the speckle.

A raw file is a flat run of samples; ``shape=(axial, lateral)`` and ``dtype`` say how to cut it.  Scanners write
it in one of two orders: *sample-major* (all lines at one depth, then the next depth: numpy's C-order of an
``(axial, lateral)`` frame, what :func:`femreg.io.read_frames` reads by default) or *line-major* (one A-line
after another: the C-order of ``(lateral, axial)``, MATLAB's column order of ``(axial, lateral)``).  An RF line
carries the transducer's carrier along its samples; neighbouring lines see correlated speckle.  From these two
facts:

* :func:`resolve_layout`: a frame read as given whose carrier runs along axis 1 holds its lines as rows.  Either
  the file is line-major with the ``shape`` given (``axial`` samples per line), or the two sizes were given the
  other way round.  The reading whose neighbouring lines correlate is kept and ``metadata["layout"]`` says so;
  when neither correlates the choice is refused, naming both shapes.
* :func:`byte_order_hint`: samples without a carrier (or not finite) that show one in the other byte order.
* :func:`shows_carrier`: whether a file's first frame read as a given sample type carries an RF carrier.
* :func:`dtype_hint`: samples without a carrier (or not finite) whose bytes show one read as another sample type
  (a float64 file read as float32 holds twice the frames, none of them RF).
* :func:`guess_shape`: for a file read without ``shape``, the lines per depth (sample-major) or samples per line
  (line-major) and the sample type under which the carrier appears: the ``--shape`` to pass for one frame.

Written here rather than taken from a library: no reader of headerless RF guesses its layout.
"""
from __future__ import annotations

import os

import numpy as np

from ..errors import InputError, pass_as

#: Neighbouring-line correlation a reading must reach, and lead the other by, to be chosen (RF, not envelope):
#: adjacent A-lines of the in vivo recordings correlate 0.38 (median), consecutive segments of one line
#: -0.01.
MIN_LINE_CORRELATION = 0.15
MIN_CORRELATION_LEAD = 0.1

#: Sample types :func:`guess_shape` tries when none is given (the common RF storage types).
GUESS_DTYPES = ("<f4", "<i2", "<f8", "<i4")


def carrier_axis(img) -> int | None:
    """0 or 1: the axis of a 2D reading along which an RF carrier runs (:func:`femreg.orientation.carrier_ratio`
    below :data:`femreg.orientation.CARRIER_RATIO`), None for neither (scrambled, envelope, too small)."""
    from ..orientation import CARRIER_RATIO, axial_carrier_ratio

    img = np.asarray(img, float)
    if not np.all(np.isfinite(img)):
        return None
    if axial_carrier_ratio(img) < CARRIER_RATIO:
        return 0
    if axial_carrier_ratio(img.T) < CARRIER_RATIO:
        return 1
    return None


def line_correlation(lines) -> float:
    """Median normalised correlation of each row of ``lines`` (n, samples) with the next: about 0 for rows that
    are not neighbouring A-lines.  NaN with fewer than 2 rows."""
    a = np.asarray(lines, float)
    if a.ndim != 2 or a.shape[0] < 2 or a.shape[1] < 2:
        return float("nan")
    a = a[: min(a.shape[0], 256)]
    a = a - a.mean(axis=1, keepdims=True)
    norm = np.sqrt(np.sum(a * a, axis=1))
    ok = (norm[:-1] > 0) & (norm[1:] > 0)
    if not np.any(ok):
        return float("nan")
    c = np.sum(a[:-1] * a[1:], axis=1)[ok] / (norm[:-1] * norm[1:])[ok]
    return float(np.median(c))


#: Marks ``axis`` not given to :func:`resolve_layout` / :func:`byte_order_hint` (None is a result of
#: :func:`carrier_axis`).
_UNKNOWN = object()


def resolve_layout(arr, path="", *, axis=_UNKNOWN):
    """``arr`` (n, a, b) read in file order as the ``shape`` (a, b) given: returns (frames (n, axial, lateral),
    note) with note "" when the reading stands.  ``axis``: :func:`carrier_axis` of ``arr[0]`` when the caller
    has it already (the test is the costly part of a read).

    A carrier along axis 1 means the file holds whole A-lines.  The file order cut into rows of ``a`` samples
    (line-major, the shape as given) and into rows of ``b`` samples (the sizes given the other way round): the
    one whose neighbouring rows correlate (:func:`line_correlation`) holds the lines.  :class:`InputError` when
    neither does clearly (both shapes named)."""
    n, a, b = arr.shape
    first = arr[0]
    if axis is _UNKNOWN:
        axis = carrier_axis(first)
    if axis != 1:
        return arr, ""
    rows_b = line_correlation(first)                  # rows of b samples: the sizes given the other way round
    rows_a = line_correlation(first.reshape(b, a))    # rows of a samples: line-major with the shape as given
    best, other = (rows_a, rows_b) if rows_a >= rows_b else (rows_b, rows_a)
    if not (best >= MIN_LINE_CORRELATION and best - other >= MIN_CORRELATION_LEAD):
        raise InputError(
            f"{path}: the samples run along whole A-lines (the RF carrier follows the file order), but neither "
            f"{a} lines of {b} samples nor {b} lines of {a} samples show neighbouring lines alike (correlation "
            f"{rows_b:.2f} / {rows_a:.2f}); read it into an (axial, lateral) array yourself")
    if rows_a >= rows_b:
        note = (f"stored line by line ({b} A-lines of {a} samples, one after another): read as (axial, lateral); "
                f"neighbouring-line correlation {rows_a:.2f} against {rows_b:.2f} for the other cut")
        return np.ascontiguousarray(arr.reshape(n, b, a).transpose(0, 2, 1)), note
    note = (f"stored line by line ({a} A-lines of {b} samples): the --shape given ({a} {b}) was read as {b} "
            f"axial x {a} lateral; neighbouring-line correlation {rows_b:.2f} against {rows_a:.2f} for the other "
            f"cut")
    return np.ascontiguousarray(arr.transpose(0, 2, 1)), note


#: Frame boundaries (:func:`continued_frames`): rows (or columns) on each side compared, the match a boundary
#: must reach (1: as alike as L neighbouring rows within a frame), and how many null spreads above 0 it must lie.
CONTINUITY_ROWS, CONTINUED_MATCH, CONTINUED_SIGMAS = 48, 0.5, 5.0


def _rows_corr(a, b):
    """Normalised correlations of every row of ``a`` (p, s) with every row of ``b`` (q, s): (p, q)."""
    a = a - a.mean(axis=1, keepdims=True)
    b = b - b.mean(axis=1, keepdims=True)
    na, nb = np.sqrt(np.sum(a * a, axis=1)), np.sqrt(np.sum(b * b, axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return (a @ b.T) / np.outer(na, nb)


def _match(before, after, rho):
    """How far the rows ``after`` continue the rows ``before`` (each (L, s), ``before`` in file order): the
    correlations of row ``L-1-i`` of ``before`` with row ``j`` of ``after`` projected on ``rho[i + j + 1]``, the
    correlation of rows that far apart within a frame; 1 for a continuation, about 0 for unrelated rows."""
    c = _rows_corr(before[::-1], after)
    L = c.shape[0]
    r = rho[np.add.outer(np.arange(L), np.arange(L)) + 1]
    ok = np.isfinite(c)
    den = np.sum((r * r)[ok])
    return float(np.sum((c * r)[ok]) / den) if den > 0 else float("nan")


def continued_frames(frames) -> str:
    """A note where the frames (n, axial, lateral), n >= 2, continue one another, so that ``shape`` cut each frame
    into pieces; "" otherwise.

    Per axis, the rows (columns) of each boundary's two sides, :data:`CONTINUITY_ROWS` on each, are matched
    against the correlation of rows that far apart within the first frame (:func:`_match`: 1 where the next frame
    continues this one, 0 for unrelated rows, as separate frames' deep rows against shallow ones, or last lines
    against first).  A boundary is joined where its match is at least :data:`CONTINUED_MATCH` and
    :data:`CONTINUED_SIGMAS` times the spread of the match between unrelated blocks of the first frame (half a
    frame apart; the test is skipped where that spread leaves no room).  At least half of the first 8 boundaries
    joined: the frames are pieces, as many per frame as the longest run of joined boundaries plus one."""
    f = np.asarray(frames)
    if f.ndim != 3 or f.shape[0] < 2 or not np.all(np.isfinite(f[:9])):
        return ""
    for axis, name in ((0, "rows"), (1, "columns")):
        rows0 = np.moveaxis(f[0], axis, 0).astype(float)
        m = rows0.shape[0]
        L = min(CONTINUITY_ROWS, m // 4)
        if L < 4 or rows0.shape[1] < 8:
            continue
        z = rows0[: 512 + 2 * L] - rows0[: 512 + 2 * L].mean(axis=1, keepdims=True)
        norm = np.linalg.norm(z, axis=1)
        z /= np.where(norm > 0, norm, np.nan)[:, None]
        lags = np.array([np.nanmedian(np.sum(z[: z.shape[0] - d] * z[d:], axis=1)) for d in range(1, 2 * L)])
        rho = np.concatenate([[1.0], lags])
        starts = np.linspace(L, m // 2 - L, 8).astype(int)
        null = np.array([_match(rows0[s - L:s], rows0[s + m // 2 - L: s + m // 2], rho) for s in starts])
        spread = float(np.sqrt(np.nanmean(null ** 2)))
        bar = max(CONTINUED_MATCH, CONTINUED_SIGMAS * spread)
        if not bar < 0.9:                        # a continuation (about 1) would not stand out
            continue
        ends = np.array([_match(np.moveaxis(f[k], axis, 0)[-L:], np.moveaxis(f[k + 1], axis, 0)[:L], rho)
                         for k in range(min(f.shape[0] - 1, 8))])
        joined = np.isfinite(ends) & (ends >= bar)
        if 2 * joined.sum() < joined.size:
            continue
        run = longest = 0
        for j in joined:
            run = run + 1 if j else 0
            longest = max(longest, run)
        n, a, b = f.shape
        whole = ((longest + 1) * a, b) if axis == 0 else (a, (longest + 1) * b)
        return (f"the frames of {a} x {b} samples continue one another: {int(joined.sum())} of {joined.size} "
                f"frame boundaries join a frame's last {name} to the next frame's first (match {np.nanmax(ends):.2f} "
                f"of a continuation, unrelated {name} {spread:.2f}), so the shape cuts each frame into "
                f"{longest + 1} pieces; for frames of {whole[0]} x {whole[1]} samples pass "
                + pass_as(f"shape=({whole[0]}, {whole[1]}) (CLI: --shape {whole[0]} {whole[1]})",
                          f"--shape {whole[0]} {whole[1]}"))
    return ""


def byte_order_hint(first, dtype, *, axis=_UNKNOWN) -> str:
    """A ``--byte-order`` to pass when the first frame (a, b) as read in ``dtype`` (the stored type) shows no
    carrier or non-finite samples but shows a carrier byte-swapped; "" otherwise (one-byte types: "").
    ``axis``: :func:`carrier_axis` of ``first`` as read, when the caller has it already."""
    dt = np.dtype(dtype)
    if dt.itemsize < 2:
        return ""
    raw = np.ascontiguousarray(np.asarray(first, dtype=dt))
    with np.errstate(all="ignore"):
        swapped = raw.view(dt.newbyteorder())            # the same bytes read in the other order
        finite = bool(np.all(np.isfinite(raw))) if dt.kind == "f" else True
        if axis is _UNKNOWN:
            axis = carrier_axis(raw)
        if finite and axis is not None:
            return ""
        if carrier_axis(swapped) is None:
            return ""
    other = "little" if dt.byteorder == ">" else "big"
    return (f"the samples show an RF carrier read {other}-endian, none as read"
            f"{'' if finite else ' (non-finite values)'}: pass "
            + pass_as(f"byte_order='{other}' (CLI: --byte-order {other})", f"--byte-order {other}"))


def shows_carrier(path, shape, dtype, *, offset=0) -> bool:
    """Whether the first frame of ``shape`` (axial, lateral) in ``path`` read as ``dtype`` from byte ``offset`` is
    whole, finite, not all zero and carries an RF carrier along axis 0 (:func:`carrier_axis`)."""
    a, b = int(shape[-2]), int(shape[-1])
    with np.errstate(all="ignore"):
        first = np.fromfile(path, dtype=np.dtype(dtype), count=a * b, offset=int(offset)).astype(float)
        if first.size < a * b or not np.all(np.isfinite(first)) or not np.any(first):
            return False
        return carrier_axis(first.reshape(a, b)) == 0


def dtype_hint(path, shape, dtype, *, offset=0, axis=_UNKNOWN, first=None) -> str:
    """A ``--dtype`` to pass when the first frame of ``shape`` (axial, lateral) read as ``dtype`` shows no carrier
    or non-finite samples, but the file's bytes read as one of :data:`GUESS_DTYPES` (in the same byte order)
    show one along axis 0 and cut into whole frames of ``shape``; "" otherwise.  ``first``: the frame as read,
    ``axis``: its :func:`carrier_axis`, when the caller has them already."""
    dt = np.dtype(dtype)
    a, b = int(shape[-2]), int(shape[-1])
    try:
        size = os.path.getsize(path) - int(offset)
    except OSError:
        return ""
    with np.errstate(all="ignore"):
        if first is None:
            first = np.fromfile(path, dtype=dt, count=a * b, offset=int(offset)).reshape(a, b)
        finite = bool(np.all(np.isfinite(first))) if dt.kind == "f" else True
        if axis is _UNKNOWN:
            axis = carrier_axis(first)
        if finite and axis is not None:
            return ""
        order = ">" if dt.byteorder == ">" else "<"
        for t in GUESS_DTYPES:
            alt = np.dtype(order + t[1:])
            if alt == dt or size % (a * b * alt.itemsize):
                continue
            if shows_carrier(path, (a, b), alt, offset=offset):
                n_as, n_alt = size // (a * b * dt.itemsize), size // (a * b * alt.itemsize)
                return (f"read as {dt.name} the samples show no RF carrier"
                        f"{'' if finite else ' (non-finite values)'} and the file holds {n_as} frame(s) of "
                        f"{a} x {b}; read as {alt.name} they show one, {n_alt} frame(s): the samples look stored "
                        f"as {alt.name}, pass "
                        + pass_as(f"dtype='{alt.name}' (CLI: --dtype {alt.name})", f"--dtype {alt.name}"))
    return ""


def _divisors(n: int, low: int, high: int) -> list[int]:
    return [d for d in range(low, min(high, n) + 1) if n % d == 0]


def guess_shape(path, *, offset=0, dtype=None, byte_order=None, max_values=1 << 21) -> str:
    """The ``--shape`` (and ``--dtype`` / ``--byte-order``) under which a raw file's first samples show an RF
    carrier, as one line of advice ("" when none does).  Sample-major: the smallest line count (16-2048) whose
    rows carry it along axis 0; line-major: the line length (64-16384 samples) whose neighbouring lines
    correlate most.  Assumes one frame; with F frames the other size divides by F."""
    from .checks import parse_dtype

    try:
        size = os.path.getsize(path) - int(offset)
    except OSError:
        return ""
    types = [parse_dtype(dtype, byte_order)] if dtype is not None else [
        np.dtype(t) if byte_order is None else parse_dtype(t[1:], byte_order) for t in GUESS_DTYPES]
    if dtype is None and byte_order is None:
        types += [t.newbyteorder(">") for t in types]
    for dt in types:
        if size <= 0 or size % dt.itemsize:
            continue
        n = size // dt.itemsize
        with np.errstate(all="ignore"):
            flat = np.fromfile(path, dtype=dt, count=min(n, max_values), offset=int(offset)).astype(float)
        if not np.all(np.isfinite(flat)) or not np.any(flat):
            continue
        order = "big" if dt.byteorder == ">" else "little"
        flags = f" --dtype {dt.name}" + (" --byte-order big" if order == "big" else "")
        for lines in _divisors(n, 16, 2048):          # sample-major: rows of `lines` values, one per line
            k = min(flat.size // lines, 4096)
            if k >= 64 and carrier_axis(flat[: k * lines].reshape(k, lines)) == 0:
                return (f"{size} bytes read as {order}-endian {dt.name} show an RF carrier with {lines} lines: "
                        f"--shape {n // lines} {lines}{flags} (one frame; with F frames --shape "
                        f"{n // lines}/F {lines})")
        if flat.size >= 2048 and carrier_axis(flat[: flat.size // 512 * 512].reshape(-1, 512).T) == 0:
            best, best_c = None, -1.0
            for length in _divisors(n, 64, 16384):    # line-major: rows of `length` samples, one per line
                if flat.size >= 4 * length:
                    c = line_correlation(flat[: flat.size // length * length].reshape(-1, length))
                    if c > best_c + 1e-9:
                        best, best_c = length, c
            if best is not None and best_c >= MIN_LINE_CORRELATION:
                return (f"{size} bytes read as {order}-endian {dt.name} hold A-lines of {best} samples one after "
                        f"another (neighbouring-line correlation {best_c:.2f}): --shape {best} {n // best}{flags} "
                        f"(one frame; with F frames --shape {best} {n // best}/F)")
    return ""
