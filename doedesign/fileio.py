"""File output: atomic writes (a temporary name beside the target, then rename) and the one
strict JSON encoder (:func:`~doedesign.fileio.json_ready`, :func:`~doedesign.fileio.dumps_json`,
:func:`~doedesign.fileio.write_json`).

A failure part-way leaves no partial file behind, so a mask shop or a later
pipeline step never sees a half-written result. Temporary names are short and never end
in the final extension (``.tmp.<pid>-<random>.part``, 30 bytes at most, so any name the
file system allows can be written), so a killed run cannot leave something that looks
like a result; the next write into the same folder removes temporaries whose process is
gone. :func:`output_run` marks a folder incomplete while a command fills it, so a kill
between two outputs is visible, and removes what the command wrote when it fails.
Output paths are checked once, here (:func:`check_output_path`): a device, pipe or
socket is never replaced by a file, and names longer than the system allows are refused
as one line.
"""

from __future__ import annotations

import contextlib
import contextvars
import datetime as _dt
import json
import math
import os
import re
import stat
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from .errors import DoeError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["atomic_path", "dumps_json", "json_ready", "read_npz", "save_figure", "write_json", "write_npz",
           "check_input_file", "check_output_path", "ensure_output_dir", "ensure_output_file", "load_npy",
           "make_temporary", "output_run", "parse_json", "parse_toml", "read_json", "read_text_file", "read_toml",
           "npz_shape", "safe_file_name", "shown_path"]

TEMP_SUFFIX = ".part"
INCOMPLETE_MARKER = "INCOMPLETE"
_TEMP_NAME = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)-[^.]+" + re.escape(TEMP_SUFFIX) + "$")
# Longest file name and path (bytes) where the system does not say (Linux's NAME_MAX, PATH_MAX).
_NAME_MAX, _PATH_MAX = 255, 4096
# Results written by atomic_path inside the innermost output_run: (path, existed before).
_RUN_WRITES: contextvars.ContextVar[list | None] = contextvars.ContextVar("doe_run_writes", default=None)


def shown_path(path: str | Path, limit: int = 120) -> str:
    """``path`` for a one-line message: long paths cut in the middle, control characters escaped."""
    text = str(path)
    if len(text) > limit:
        text = f"{text[:limit // 2]}...{text[-limit // 2:]}"
    return text.encode("unicode_escape").decode("ascii") if not text.isprintable() else text


def _os_message(path, exc, doing="write"):
    return f"{shown_path(path)}: cannot {doing} ({exc.strerror or exc})"


def _limit(folder, name, default):
    try:
        return int(os.pathconf(folder, name))
    except (OSError, ValueError):
        return default


def check_output_path(path: str | Path, what: str = "--out") -> Path:
    """``path`` as a Path after checking that it names something a file may be written to.

    Refused (one line each): a NUL character, a path or one of its names longer than the
    system allows (ENAMETOOLONG would only show up after the work), and an existing
    device, pipe or socket (writing a result must never replace ``/dev/null``).
    An existing folder is left to the caller (a folder is right for ``--out DIR``).
    """
    text = os.fsencode(path) if not isinstance(path, bytes) else path
    if b"\0" in text:
        raise DoeError(f"{shown_path(path)}: {what} holds a NUL character; give a plain path")
    path = Path(path)
    folder = next((p for p in [path.absolute(), *path.absolute().parents] if _is_dir(p)), Path("/"))
    name_max, path_max = _limit(folder, "PC_NAME_MAX", _NAME_MAX), _limit(folder, "PC_PATH_MAX", _PATH_MAX)
    if len(os.fsencode(path.absolute())) >= path_max:
        raise DoeError(f"{shown_path(path)}: {what} is {len(os.fsencode(path.absolute()))} bytes long, over the "
                       f"system's {path_max}-byte path limit")
    for part in path.parts:
        if len(os.fsencode(part)) > name_max:
            raise DoeError(f"{shown_path(path)}: {what} holds a name of {len(os.fsencode(part))} bytes, over the "
                           f"file system's {name_max}-byte limit")
    try:
        st = os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        return path
    except OSError as exc:
        raise DoeError(_os_message(path, exc, f"use {what}")) from None
    if not (stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode)):
        raise DoeError(f"{shown_path(path)}: {what} is not a regular file (a device, pipe or socket); "
                       "give a new file name or a regular file")
    return path


def _is_dir(path):
    try:
        return stat.S_ISDIR(os.stat(path).st_mode)
    except OSError:
        return False


def safe_file_name(text: str, suffix: str = "", fallback: str = "design") -> str:
    """A file name made from ``text`` (a design's name, say) followed by ``suffix``.

    Path separators and control characters (NUL included) become ``_``, leading dots are
    dropped (no hidden files), and the name is cut at a character boundary so that
    name and suffix fit the file system's 255-byte limit. An empty result is ``fallback``.
    """
    name = re.sub(r"[\x00-\x1f\x7f/\\]", "_", str(text)).lstrip(". ").rstrip()
    budget = _NAME_MAX - len(os.fsencode(suffix))
    raw = name.encode("utf-8", "surrogateescape")[:max(budget, 1)]
    name = raw.decode("utf-8", "ignore").rstrip()
    return (name or fallback) + suffix


def _pid_alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temporaries(folder: str | Path) -> list[str]:
    """Delete the temporaries of killed writers in ``folder``; returns the names removed.

    Only files named like :func:`atomic_path`'s temporaries whose writing process no longer
    exists are removed, so a concurrent writer's temporary survives.
    """
    removed: list[str] = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        match = _TEMP_NAME.match(entry.name)
        if match and entry.is_file(follow_symlinks=False) and not _pid_alive(int(match["pid"])):
            with contextlib.suppress(OSError):
                os.unlink(entry.path)
                removed.append(entry.name)
    return removed


def ensure_output_dir(path: str | Path, what: str = "--out", create: bool = False) -> Path:
    """Check that the output folder ``path`` can be written (created when ``create``).

    Called before long work, so a bad ``--out`` costs nothing. Without ``create`` a missing
    folder is not made (a refused run leaves nothing); its nearest existing parent must be
    a writable folder.

    Raises
    ------
    DoeError
        ``path`` is an existing file, cannot be created, or is not writable (one line).
    """
    path = check_output_path(path, what)
    if path.exists() and not path.is_dir():
        raise DoeError(f"{shown_path(path)}: {what} is an existing file; it must be a folder")
    if create:
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DoeError(_os_message(path, exc, "create the output folder")) from None
    existing = path.absolute()
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise DoeError(f"{path}: cannot create the output folder ({existing} is a file)")
    if not os.access(existing, os.W_OK | os.X_OK) or _read_only_mount(existing):
        raise DoeError(f"{path}: cannot create the output folder ({existing} is not writable)"
                       if existing != path.absolute() else f"{path}: output folder is not writable")
    return path


def _read_only_mount(path):
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except OSError:
        return False


def ensure_output_file(path: str | Path, what: str = "--out") -> Path:
    """Check before long work that the file ``path`` can be written (its folder is created).

    Raises
    ------
    DoeError
        A folder, a device, a pipe or a socket sits at ``path``, the path is too long, or its
        folder cannot be created or written.
    """
    path = check_output_path(path, what)
    if path.is_dir():
        raise DoeError(f"{shown_path(path)}: {what} is an existing folder; it must be a file name")
    ensure_output_dir(path.parent if str(path.parent) else Path("."), f"the folder of {what}")
    return path


@contextlib.contextmanager
def output_run(folder: str | Path, command: str, keep_partial: bool = False) -> Iterator[Path]:
    """Mark ``folder`` incomplete while ``command`` writes its outputs there.

    The marker file ``INCOMPLETE_MARKER`` is written first and removed only when the
    block finishes without an exception, so after a kill or a failure the folder says that
    its files may come from different runs. When the block fails with an error (a full
    disk, a refused input), the results it wrote through :func:`atomic_path` that did not
    exist before are removed again (unless ``keep_partial``: resumable work such as
    finished Monte Carlo samples is kept, under the marker); the marker stays only while
    something of this run remains (a result it replaced, kept work) or when it was
    interrupted (Ctrl-C). A failure that leaves the folder as it was leaves nothing behind.
    """
    folder = Path(folder)
    created = not folder.exists()
    folder = ensure_output_dir(folder, create=True)
    remove_stale_temporaries(folder)
    marker = folder / INCOMPLETE_MARKER
    before = _snapshot(folder)
    started = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    try:
        with atomic_path(marker) as tmp:
            tmp.write_text(f"`{command}` started {started} UTC (pid {os.getpid()}) and has not finished: "
                           "the files in this folder may be partial or from different runs.\n")
    except DoeError:
        if created:
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
    written: list = []
    token = _RUN_WRITES.set(written)
    try:
        yield folder
    except BaseException as exc:
        if isinstance(exc, Exception) and not keep_partial:
            for path, existed in written:
                if not existed:
                    with contextlib.suppress(OSError):
                        os.unlink(path)
        if _snapshot(folder) == before:
            marker.unlink(missing_ok=True)
            if created:
                with contextlib.suppress(OSError):
                    folder.rmdir()
        raise
    finally:
        _RUN_WRITES.reset(token)
    outer = _RUN_WRITES.get()
    if outer is not None:
        outer.extend(written)
    marker.unlink(missing_ok=True)


def _snapshot(folder):
    """Names, sizes and times of the results in ``folder`` (not the marker or temporaries)."""
    out = {}
    for entry in os.scandir(folder):
        if entry.name != INCOMPLETE_MARKER and not _TEMP_NAME.match(entry.name):
            st = entry.stat(follow_symlinks=False)
            out[entry.name] = (st.st_size, st.st_mtime_ns)
    return out


def make_temporary(folder: str | Path) -> Path:
    """A new empty file ``.tmp.<pid>-<random>.part`` in ``folder`` (at most 30 bytes of name).

    Named so that ``remove_stale_temporaries`` removes it once its process is gone, and
    short so that it fits wherever the final name fits.
    """
    fd, tmp = tempfile.mkstemp(prefix=f".tmp.{os.getpid()}-", suffix=TEMP_SUFFIX, dir=folder)
    os.close(fd)
    return Path(tmp)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    The temporary is ``.tmp.<pid>-<random>.part`` (never the final extension; writers that
    pick a format from the name must be told the format or given an open file). Any
    operating-system error while writing (full disk, file-size limit, read-only folder)
    becomes one :class:`~doedesign.errors.DoeError` naming ``path``; the temporary is removed.

    Parameters
    ----------
    path : str or Path
        Final destination.

    Yields
    ------
    Path
        Where the caller must write. It is removed if the block raises.

    Raises
    ------
    DoeError
        The folder cannot be created or written, a folder, device, pipe or socket sits at
        ``path``, or writing failed.
    """
    path = check_output_path(path, "the result path")
    if path.is_dir():
        raise DoeError(f"{shown_path(path)}: the result path is taken by a folder")
    existed = path.exists()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(path.parent)
        tmp = make_temporary(path.parent)
    except OSError as exc:
        raise DoeError(_os_message(path, exc)) from None
    try:
        # mkstemp creates 0600; give the result the permissions a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        yield tmp
        os.replace(tmp, path)
    except OSError as exc:
        raise DoeError(_os_message(path, exc)) from None
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
    writes = _RUN_WRITES.get()
    if writes is not None:
        writes.append((path, existed))


# Largest array an input file may make the tool allocate (claimed sizes are checked first).
MAX_INPUT_ARRAY_BYTES = 512 * 1024**2


def check_input_file(path: str | Path, error: type[Exception] | None = None) -> Path:
    """``path`` as a Path after checking it is an existing regular file.

    Named pipes, devices and folders are refused (reading a pipe would wait forever).
    """
    error = error or DoeError
    path = Path(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except OSError as exc:
        raise error(_os_message(path, exc, "read")) from None
    if not stat.S_ISREG(st.st_mode):
        kind = "a folder" if stat.S_ISDIR(st.st_mode) else "not a regular file (a pipe, socket or device)"
        raise error(f"{path}: is {kind}; give a file")
    return path


# Largest text input (a TOML spec or configuration, a JSON report) read whole: a 2 GB file
# claiming to be a spec is refused from its size before it is read.
MAX_TEXT_BYTES = 16 * 1024**2


def read_text_file(path: str | Path, what: str = "text file", error: type[Exception] | None = None,
                   max_bytes: int = MAX_TEXT_BYTES) -> str:
    """The UTF-8 text of ``path`` after checking it is a regular file of at most ``max_bytes``."""
    error = error or DoeError
    path = check_input_file(path, error)
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size > max_bytes:
                raise error(f"{shown_path(path)}: {format(size, ',')} bytes is too large for a {what} "
                            f"(at most {max_bytes // 1024**2} MiB)")
            data = fh.read(max_bytes + 1)
    except OSError as exc:
        raise error(_os_message(path, exc, "read")) from None
    if len(data) > max_bytes:
        raise error(f"{shown_path(path)}: too large for a {what} (at most {max_bytes // 1024**2} MiB)")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{shown_path(path)}: not a {what}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None


def read_toml(path: str | Path, what: str = "TOML file", error: type[Exception] | None = None) -> dict:
    """A TOML file as a dict: its size checked before it is read, then :func:`parse_toml`."""
    return parse_toml(read_text_file(path, what, error), str(path), error)


def read_json(path: str | Path, what: str = "JSON file", error: type[Exception] | None = None) -> Any:
    """A JSON file's value: its size checked before it is read, then :func:`parse_json`."""
    return parse_json(read_text_file(path, what, error), str(path), error)


def check_npy_header(fh: IO[bytes], available_bytes: int, where: str,
                     error: type[Exception] | None = None) -> tuple[tuple[int, ...], np.dtype]:
    """Read an ``.npy`` header from ``fh`` and check its claimed size before anything is allocated.

    Parameters
    ----------
    fh : file object positioned at the start of the ``.npy`` data
    available_bytes : int
        Bytes of the member or file, header included.
    where : str
        The file (and member) for messages.

    Returns
    -------
    (shape, dtype)

    Raises
    ------
    error
        Object arrays (never unpickled), a claimed size beyond the data present or beyond
        ``MAX_INPUT_ARRAY_BYTES``.
    """
    error = error or DoeError
    fmt = np.lib.format
    try:
        version = fmt.read_magic(fh)
        shape, fortran, dtype = (fmt.read_array_header_1_0(fh) if version == (1, 0)
                                 else fmt.read_array_header_2_0(fh))
    except (ValueError, OSError, EOFError, SyntaxError) as exc:
        raise error(f"{where}: not a numpy array: {exc}") from None
    if dtype.hasobject:
        raise error(f"{where}: holds Python objects (dtype {dtype}); only numeric and text arrays are read")
    claimed = int(np.prod(shape, dtype=object)) * dtype.itemsize
    present = available_bytes - fh.tell()
    if claimed > MAX_INPUT_ARRAY_BYTES:
        raise error(f"{where}: claims {shape} {dtype} = {claimed / 1e9:.3g} GB, over the "
                    f"{MAX_INPUT_ARRAY_BYTES / 1e9:.3g} GB input limit")
    if claimed > present:
        raise error(f"{where}: header claims {shape} {dtype} ({claimed} bytes) but only {present} bytes "
                    "follow (truncated or corrupted)")
    return shape, dtype


def _check_npz_members(path, error):
    import zipfile

    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            if not info.filename.endswith(".npy"):
                continue
            where = f"{path}: array '{info.filename[:-4]}'"
            if info.file_size > MAX_INPUT_ARRAY_BYTES + 65536:
                raise error(f"{where} inflates to {info.file_size / 1e9:.3g} GB, over the "
                            f"{MAX_INPUT_ARRAY_BYTES / 1e9:.3g} GB input limit")
            with zf.open(info) as fh:
                check_npy_header(fh, info.file_size, where, error)


def npz_shape(path: str | Path, name: str) -> tuple[int, ...] | None:
    """The shape member ``name`` of an ``.npz`` claims, read from its header alone (nothing
    inflated), so a size check can refuse a file before it is loaded; None where the file or
    member cannot be read that way (the loader then reports it)."""
    import zipfile

    try:
        path = check_input_file(path)  # a named pipe would block the zip reader forever
        with zipfile.ZipFile(path) as zf:
            info = zf.getinfo(f"{name}.npy")
            with zf.open(info) as fh:
                shape, _ = check_npy_header(fh, info.file_size, f"{path}: array '{name}'")
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, DoeError):
        return None
    return tuple(int(v) for v in shape)


def load_npy(path: str | Path, error: type[Exception] | None = None) -> np.ndarray:
    """A bare ``.npy`` array after checking the file and its claimed size (never unpickles)."""
    error = error or DoeError
    path = check_input_file(path, error)
    try:
        with open(path, "rb") as fh:
            check_npy_header(fh, os.fstat(fh.fileno()).st_size, str(path), error)
            fh.seek(0)
            return np.load(fh, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise error(f"{path}: not a readable .npy array: {exc}") from None


def read_npz(path: str | Path, required: Iterable[str], what: str,
             error: type[Exception] | None = None) -> dict[str, np.ndarray]:
    """All arrays of an ``.npz`` after checking the ``required`` fields.

    Claimed array sizes are checked against the data present and
    ``MAX_INPUT_ARRAY_BYTES`` before anything is inflated. Errors (of class ``error``,
    default :class:`~doedesign.errors.DoeError`) name the file, say it is not a ``what``
    and list what is missing.
    """
    import zipfile

    error = error or DoeError
    path = check_input_file(path, error)
    try:
        _check_npz_members(path, error)
        with np.load(path, allow_pickle=False) as npz:
            data = {k: npz[k] for k in npz.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, NotImplementedError) as exc:
        raise error(f"{path}: not a {what} (.npz): {exc}") from None
    missing = [k for k in required if k not in data]
    if missing:
        raise error(f"{path}: missing field(s) {', '.join(missing)}; a {what} needs {', '.join(required)}")
    return data


def parse_json(text: str, where: str, error: type[Exception] | None = None) -> Any:
    """JSON text from a user's file, parsed; every failure is one ``error`` naming ``where``.

    Besides syntax errors this catches what :func:`json.loads` raises on hostile input:
    RecursionError for arrays nested thousands deep and ValueError for integers over
    Python's digit limit.
    """
    error = error or DoeError
    try:
        return json.loads(text)
    except RecursionError:
        raise error(f"{where} is not readable JSON (nested too deeply)") from None
    except ValueError as exc:  # JSONDecodeError, an integer of over 4300 digits
        raise error(f"{where} is not valid JSON ({exc})") from None


def parse_toml(text: str, where: str, error: type[Exception] | None = None) -> dict[str, Any]:
    """TOML text from a user's file, parsed; every failure is one ``error`` naming ``where``
    (syntax, tables nested too deeply for the parser, integers over the digit limit)."""
    import tomllib

    error = error or DoeError
    try:
        return tomllib.loads(text)
    except RecursionError:
        raise error(f"{where} is not readable TOML (nested too deeply)") from None
    except ValueError as exc:  # TOMLDecodeError, an integer of over 4300 digits
        raise error(f"{where} is not valid TOML ({exc})") from None


def json_ready(obj: Any) -> Any:
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


def dumps_json(obj: Any, indent: int | None = 2) -> str:
    """Strict JSON text of ``obj`` (see :func:`json_ready`)."""
    return json.dumps(json_ready(obj), indent=indent, allow_nan=False)


def write_json(path: str | Path, obj: Any) -> Path:
    """Write ``obj`` as indented strict JSON (:func:`dumps_json`), atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(dumps_json(obj) + "\n")
    return Path(path)


def write_npz(path: str | Path, **arrays: ArrayLike) -> Path:
    """Write an uncompressed ``.npz`` atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, allow_pickle=True, **arrays)
    return Path(path)


def save_figure(fig: Figure, path: str | Path, dpi: int = 110) -> Path:
    """Save a matplotlib figure atomically as PNG and close it."""
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format="png")
    plt.close(fig)
    return Path(path)
