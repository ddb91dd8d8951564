"""Reading GDSII/OASIS back: a vectorized GDSII BOUNDARY reader written apart from the
writer (:mod:`masks.gds_records` shares only the record-type numbers of the format), and
gdstk for OASIS and whole libraries.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import gdstk
import numpy as np

from doedesign.errors import DoeError

from .gds_records import BOUNDARY, DATATYPE, ENDEL, ENDLIB, ENDSTR, LAYER, STRNAME, UNITS, XY, real8
from .grid import PRECISION_M, UNIT_M

__all__ = ["GdsBoundaries", "OASIS_MAGIC", "is_oasis", "read_boundaries", "read_gds_boundaries", "read_library"]

OASIS_MAGIC = b"%SEMI-OASIS\r\n"


def is_oasis(path: str | Path) -> bool:
    """True when the file starts with the OASIS magic (by content: temporaries have no extension)."""
    try:
        with open(path, "rb") as fh:
            return fh.read(len(OASIS_MAGIC)) == OASIS_MAGIC
    except OSError as exc:
        raise DoeError(f"{path}: cannot read ({exc.strerror or exc})") from None


def read_library(path: str | Path) -> gdstk.Library:
    """Read a GDSII (``.gds``) or OASIS (``.oas``) file with gdstk; DoeError if unreadable."""
    path = Path(path)
    try:
        if is_oasis(path):
            return gdstk.read_oas(str(path))
        return gdstk.read_gds(str(path))
    except (OSError, RuntimeError) as exc:
        raise DoeError(f"{path}: cannot read as GDSII/OASIS: {exc}") from None


@dataclass
class GdsBoundaries:
    """BOUNDARY elements of one GDSII file, read with numpy (see :func:`read_gds_boundaries`).

    Attributes
    ----------
    dbu_m : float
        Database unit in metres (from the UNITS record).
    cells : dict
        Structure name -> dict of arrays ``layer``, ``datatype``, ``counts`` (points per
        element, closing point dropped) and ``first`` (byte offset of each element's first
        point in the file, or its index into a ``points`` array when read by gdstk);
        :meth:`points` reads the vertices of chosen elements.
    """

    dbu_m: float
    cells: dict
    _words: tuple = ()  # big-endian int32 views of the file at byte offsets 0 and 2

    def points(self, cell: str, select: np.ndarray | None = None) -> np.ndarray:
        """Vertices (int64 (n, 2), database units) of the selected elements of ``cell``."""
        c = self.cells[cell]
        sel = np.arange(c["counts"].size) if select is None else np.asarray(select)
        counts = c["counts"][sel]
        first = c["first"][sel]
        out = np.empty((int(counts.sum()), 2), np.int64)
        ends = np.cumsum(counts)
        if "points" in c:
            out[:] = c["points"][np.repeat(first - (ends - counts), counts) + np.arange(out.shape[0])]
            return out
        # An element is a whole number of 4-byte words, so its points keep its alignment.
        aligned_pt = np.repeat(first % 4 == 0, counts)
        for aligned, words in zip((True, False), self._words):
            pick = aligned_pt == aligned
            if not pick.any():
                continue
            start = (first - (0 if aligned else 2)) // 4 - 2 * (ends - counts)
            idx = (np.repeat(start, counts) + 2 * np.arange(out.shape[0]))[pick]
            out[pick, 0] = words[idx]
            out[pick, 1] = words[idx + 1]
        return out


def read_gds_boundaries(path: str | Path) -> GdsBoundaries:
    """Every BOUNDARY of a GDSII file, grouped by structure, with a vectorized record reader.

    Candidate elements are found where a BOUNDARY header is followed by LAYER, DATATYPE, XY
    and ENDEL headers at the offsets their lengths imply; a record-by-record walk from the
    start of the file then accepts only candidates it lands on, jumping over each run of
    back-to-back candidates in one step, so bytes that merely look like a header inside
    coordinate data are never taken as one.

    Raises
    ------
    DoeError
        When the file is not a well-formed GDSII stream.
    """
    path = Path(path)
    try:
        raw = np.memmap(path, dtype=np.uint8, mode="r")
    except (OSError, ValueError) as exc:
        raise DoeError(f"{path}: cannot read as GDSII: {exc}") from None
    size = raw.size - raw.size % 2
    w = raw[:size].view(">u2")  # records start on even offsets
    # int32 views at byte offsets 0 and 2 (mod 4) for aligned reads anywhere
    v32 = tuple(raw[off:off + (size - off) // 4 * 4].view(">i4") for off in (0, 2))

    def word32(p):  # big-endian int32 at even byte offsets p
        out = np.empty(p.shape, np.int64)
        odd = (p % 4) != 0
        out[~odd] = v32[0][p[~odd] // 4]
        out[odd] = v32[1][(p[odd] - 2) // 4]
        return out

    # BOUNDARY header bytes 00 04 08 00 at either alignment
    key = np.frombuffer(b"\x00\x04\x08\x00", "<u4")[0]
    cand = np.concatenate([np.nonzero(v.view("<u4") == key)[0] * 4 + off
                           for off, v in zip((0, 2), v32)])
    cand.sort()
    cand = cand[cand + 24 <= size]
    cand = cand[(word32(cand + 4) == (6 << 16 | LAYER)) & (w[(cand + 10) // 2] == 6)
                & (w[(cand + 12) // 2] == DATATYPE) & (w[(cand + 18) // 2] == XY)]
    xy_len = w[(cand + 16) // 2].astype(np.int64)
    ok = (xy_len >= 4 + 8 * 4) & ((xy_len - 4) % 8 == 0) & (cand + 20 + xy_len <= size)
    cand, xy_len = cand[ok], xy_len[ok]
    ok = word32(cand + 16 + xy_len) == (4 << 16 | ENDEL)
    cand, xy_len = cand[ok], xy_len[ok]
    end = cand + 20 + xy_len
    # runs of candidates each starting where the previous one ends
    brk = np.ones(cand.size, bool)
    brk[1:] = end[:-1] != cand[1:]
    run = np.cumsum(brk) - 1
    run_last = np.append(np.nonzero(brk)[0][1:] - 1, cand.size - 1)
    accepted = np.zeros(cand.size, bool)
    cell_of = np.full(cand.size, -1, np.int64)
    names, dbu_m, current, pos = [], None, -1, 0
    header = bytes(raw[:min(size, 4)])
    while pos + 4 <= size:
        i = int(np.searchsorted(cand, pos))
        if i < cand.size and cand[i] == pos:
            last = run_last[run[i]]
            if current < 0:
                raise DoeError(f"{path}: BOUNDARY outside any structure at byte {pos}")
            accepted[i:last + 1] = True
            cell_of[i:last + 1] = current
            pos = int(end[last])
            continue
        length, rtype = int(w[pos // 2]), int(w[pos // 2 + 1])
        if length < 4 or pos + length > raw.size:
            raise DoeError(f"{path}: corrupt GDSII record at byte {pos}")
        if rtype == BOUNDARY:
            raise DoeError(f"{path}: BOUNDARY at byte {pos} has records this reader does not "
                           "expect (only LAYER, DATATYPE, XY)")
        if rtype == STRNAME:
            names.append(bytes(raw[pos + 4:pos + length]).rstrip(b"\0").decode("ascii", "replace"))
            current = len(names) - 1
        elif rtype == ENDSTR:
            current = -1
        elif rtype == UNITS:  # user unit, database unit in metres
            dbu_m = real8(bytes(raw[pos + 12:pos + 20]))
        elif rtype == ENDLIB:
            break
        pos += length
    if header[2:4] != b"\x00\x02" or dbu_m is None:
        raise DoeError(f"{path}: not a GDSII stream (no HEADER/UNITS record)")
    cand, xy_len, cell_of = cand[accepted], xy_len[accepted], cell_of[accepted]
    layer = w[(cand + 8) // 2].astype(np.int16)
    datatype = w[(cand + 14) // 2].astype(np.int16)
    counts = (xy_len - 4) // 8 - 1  # the closing point repeats the first
    cells = {}
    for k, name in enumerate(names):
        sel = np.nonzero(cell_of == k)[0]
        cells[name] = {"layer": layer[sel].astype(np.int64), "datatype": datatype[sel].astype(np.int64),
                       "counts": counts[sel], "first": cand[sel] + 20}
    return GdsBoundaries(dbu_m, cells, v32)


def read_boundaries(path: str | Path) -> GdsBoundaries:
    """:class:`GdsBoundaries` of a .gds (numpy reader) or .oas (gdstk) file, in 1 nm units."""
    path = Path(path)
    if not is_oasis(path):
        read = read_gds_boundaries(path)
        if abs(read.dbu_m - PRECISION_M) > 1e-6 * PRECISION_M:
            raise DoeError(f"{path}: database unit {read.dbu_m:g} m, expected {PRECISION_M:g} m")
        return read
    cells = {}
    for c in read_library(path).cells:
        if not isinstance(c, gdstk.Cell):  # a file read whole holds no raw cells
            continue
        polys = c.polygons
        pts = [p.points for p in polys]
        counts = np.array([len(q) for q in pts], np.int64)
        cells[c.name] = {
            "layer": np.array([p.layer for p in polys], np.int64),
            "datatype": np.array([p.datatype for p in polys], np.int64),
            "counts": counts, "first": np.cumsum(counts) - counts,
            "points": (np.rint(np.concatenate(pts) * (UNIT_M / PRECISION_M)).astype(np.int64)
                       if pts else np.zeros((0, 2), np.int64))}
    return GdsBoundaries(PRECISION_M, cells)
