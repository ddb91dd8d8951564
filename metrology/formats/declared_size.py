"""What a file's header declares against what the file holds, where the reading library checks
only part of it.

- Nanosurf ``.nid``: SurfaceTopography checks the length of the one frame it reads, so a file
  cut inside a later frame (the backward scan, an amplitude channel) reads without error. The
  header's frames (points x lines x bytes per point of every frame its groups list) are summed
  here and compared with the bytes after the ``#!`` marker. SurfaceTopography keeps the parsed
  header private and lists only the frames in a length unit, hence the few lines that parse the
  INI-style header here (bounded to ``NID_MAX_HEADER_BYTES``, nothing allocated from it).
- Dektak CSV: a file cut at a line end parses as a shorter scan. The points times the sample
  spacing must cover the ``Length`` the header declares (to one sample and the printed rounding).
"""

from __future__ import annotations

import re
from pathlib import Path

from metrology.formats.measurement import MeasurementFileError

__all__ = ["NID_MAX_HEADER_BYTES", "check_dektak_length", "check_nid_frames", "nid_frames"]

# Real .nid headers are 5-40 kB (the three test files: 4.9, 4.9 and 30.7 kB); a header is
# searched for the data marker in at most this many bytes.
NID_MAX_HEADER_BYTES = 16 * 2**20
_NID_MARKER = b"#!"
_FRAME_KEY = re.compile(r"Gr(\d+)-Ch(\d+)$")
_LENGTH = re.compile(r"\s*([-+0-9.eE]+)\s*(\S+)\s*$")
_LENGTH_UNITS_M = {"nm": 1e-9, "um": 1e-6, "µm": 1e-6, "μm": 1e-6, "mm": 1e-3, "m": 1.0}


def _count(path: Path, section: str, key: str, value: str | None) -> int:
    try:
        number = int(str(value).strip())
    except ValueError:
        raise MeasurementFileError(f"{path}: header [{section}] {key}={value!r} is not a count") from None
    if number < 0:
        raise MeasurementFileError(f"{path}: header [{section}] {key}={number} is negative")
    return number


def nid_frames(path: str | Path) -> tuple[int, list[tuple[str, int]]]:
    """Where a ``.nid`` file's data start and the bytes of each frame its header declares.

    Returns
    -------
    data_start : int
        Offset of the first data byte (after the ``#!`` marker).
    frames : list of (str, int)
        Each frame the groups list (``Gr<i>-Ch<j>`` for ``i < GroupCount``, ``j < Gr<i>-Count``)
        as (section name, Points x Lines x SaveBits / 8), in the header's order.

    Raises
    ------
    MeasurementFileError
        No data marker within ``NID_MAX_HEADER_BYTES``, or a count that is not one.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(NID_MAX_HEADER_BYTES)
    if head.startswith(_NID_MARKER):
        marker = 0
    else:
        marker = head.find(b"\n" + _NID_MARKER)
        if marker < 0:
            raise MeasurementFileError(f"{path}: no '#!' data marker in the first "
                                       f"{min(len(head), NID_MAX_HEADER_BYTES)} bytes (not a complete .nid)")
        marker += 1
    sections: dict[str, dict[str, str]] = {}
    current = sections.setdefault("DataSet", {})
    for line in head[:marker].decode("latin-1").splitlines():
        line = line.strip()
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
        elif "=" in line:
            key, value = line.split("=", 1)
            current[key] = value
    dataset = sections.get("DataSet", {})
    groups = _count(path, "DataSet", "GroupCount", dataset.get("GroupCount", "0"))
    frames = []
    for key, name in dataset.items():
        match = _FRAME_KEY.match(key)
        if not match:
            continue
        group, channel = int(match.group(1)), int(match.group(2))
        if group >= groups or channel >= _count(path, "DataSet", f"Gr{group}-Count",
                                                dataset.get(f"Gr{group}-Count", "0")):
            continue
        frame = sections.get(name)
        if frame is None:  # a listed frame without a section holds no data (as the reader skips it)
            continue
        bits = _count(path, name, "SaveBits", frame.get("SaveBits"))
        if bits == 0 or bits % 8:
            raise MeasurementFileError(f"{path}: header [{name}] SaveBits={bits} is not a whole number of bytes")
        size = (_count(path, name, "Points", frame.get("Points")) * _count(path, name, "Lines", frame.get("Lines"))
                * (bits // 8))
        frames.append((name, size))
    return marker + len(_NID_MARKER), frames


def check_nid_frames(path: str | Path) -> int:
    """Refuse a ``.nid`` whose data are shorter than the frames its header declares.

    Returns
    -------
    int
        The declared data bytes.

    Raises
    ------
    MeasurementFileError
        The file ends inside its data frames (truncated), naming the frame it ends in.
    """
    path = Path(path)
    start, frames = nid_frames(path)
    present = path.stat().st_size - start
    declared, end = 0, 0
    for name, size in frames:
        end += size
        if end > present:
            raise MeasurementFileError(
                f"{path}: truncated: the header declares {sum(s for _, s in frames)} bytes of data in "
                f"{len(frames)} frames, the file holds {present} after '#!' (it ends inside frame [{name}])")
        declared = end
    return declared


def check_dektak_length(path: str | Path, header: dict, points: int, step_m: float) -> float | None:
    """Refuse a Dektak scan whose points do not cover the ``Length`` its header declares.

    Parameters
    ----------
    header : dict
        The header's key-value pairs (``Length`` as the Dektak prints it, "1500.0 um").
    points, step_m : int, float
        Profile points read and their sample spacing in metres.

    Returns
    -------
    float or None
        The declared length in metres; None when the header gives none (nothing to check).

    Raises
    ------
    MeasurementFileError
        The points cover less or more than the declared length by more than one sample and
        the printed rounding of the length (a file cut at a line end, or a corrupt header).
    """
    text = header.get("Length")
    if text is None:
        return None
    match = _LENGTH.match(str(text))
    if match is None or match.group(2) not in _LENGTH_UNITS_M:
        return None
    try:
        length = float(match.group(1)) * _LENGTH_UNITS_M[match.group(2)]
    except ValueError:
        return None
    number = match.group(1)
    decimals = len(number.split(".", 1)[1]) if "." in number and "e" not in number.lower() else 0
    rounding = 0.5 * 10.0 ** -decimals * _LENGTH_UNITS_M[match.group(2)]
    covered = points * step_m
    if abs(covered - length) > step_m + rounding:
        raise MeasurementFileError(f"{path}: the scan data cover {covered * 1e6:.6g} um ({points} points of "
                                   f"{step_m * 1e6:.6g} um) but the header's Length is {text.strip()} "
                                   f"(truncated or corrupt)")
    return length
