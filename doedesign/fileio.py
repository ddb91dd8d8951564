"""File output: atomic writes (a temporary name beside the target, then rename) and the one
strict JSON encoder (:func:`json_ready`, :func:`dumps_json`, :func:`write_json`).

A failure part-way leaves no partial file behind, so a mask shop or a later
pipeline step never sees a half-written result.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["atomic_path", "dumps_json", "json_ready", "read_npz", "save_figure", "write_json", "write_npz"]


@contextlib.contextmanager
def atomic_path(path, suffix=None):
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    Parameters
    ----------
    path : str or Path
        Final destination.
    suffix : str, optional
        Suffix of the temporary file (some writers pick the format from it);
        defaults to the destination's suffix plus ``.tmp``.

    Yields
    ------
    Path
        Where the caller must write. It is removed if the block raises.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix is None:
        suffix = path.suffix + ".tmp"
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    # mkstemp creates 0600; give the result the permissions a plain open() would.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def read_npz(path, required, what, error=None):
    """All arrays of an ``.npz`` after checking the ``required`` fields.

    Errors (of class ``error``, default :class:`~doedesign.errors.DoeError`) name the file,
    say it is not a ``what`` and list what is missing.
    """
    import zipfile

    from .errors import DoeError

    error = error or DoeError
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as npz:
            data = {k: npz[k] for k in npz.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise error(f"{path}: not a {what} (.npz): {exc}") from None
    missing = [k for k in required if k not in data]
    if missing:
        raise error(f"{path}: missing field(s) {', '.join(missing)}; a {what} needs {', '.join(required)}")
    return data


def json_ready(obj):
    """``obj`` as plain JSON values, the one rule for every report and JSON string we write.

    numpy scalars and arrays become Python numbers and lists, tuples lists, paths strings,
    dictionary keys strings, and NaN or infinite floats ``None`` (strict JSON has no NaN or
    Infinity, and strict readers such as jq and browsers reject them).

    Raises
    ------
    TypeError
        An object with no JSON form.
    """
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.generic):
        return json_ready(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Path):
        return str(obj)
    if obj is None or isinstance(obj, (bool, int, str)):
        return obj
    raise TypeError(f"not JSON serializable: {type(obj).__name__}")


def dumps_json(obj, indent: int | None = 2) -> str:
    """Strict JSON text of ``obj`` (see :func:`json_ready`)."""
    return json.dumps(json_ready(obj), indent=indent, allow_nan=False)


def write_json(path, obj) -> Path:
    """Write ``obj`` as indented strict JSON (:func:`dumps_json`), atomically."""
    with atomic_path(path, suffix=".json.tmp") as tmp:
        tmp.write_text(dumps_json(obj) + "\n")
    return Path(path)


def write_npz(path, **arrays):
    """Write an uncompressed ``.npz`` atomically."""
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez(tmp, **arrays)
    return Path(path)


def save_figure(fig, path, dpi=110):
    """Save a matplotlib figure atomically as PNG and close it."""
    import matplotlib.pyplot as plt

    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format="png")
    plt.close(fig)
    return Path(path)
