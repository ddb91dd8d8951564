"""Every size check counts the limits the process runs under (issue 51): under a 3 GB address-space
limit (``ulimit -v``, as shared machines and batch queues set) a command whose work would not fit
is refused before it allocates, in one line naming the limit and the size asked (exit 2, no
traceback, no output), and a MemoryError that no estimate foresaw becomes the same kind of line.
"""

import io
import resource
import subprocess
import sys
import zipfile

import numpy as np
import pytest

from doedesign import budget
from doedesign.camera import Camera
from doedesign.design import Design

LIMIT = 3 * 10 ** 9
PITCH = 5.4e-6
STEP = Design(np.zeros((2, 2)), PITCH).level_step_m()


def _limited(args, cwd):
    """``doe ARGS`` in a subprocess under RLIMIT_AS = 3 GB."""
    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (LIMIT, LIMIT))

    return subprocess.run([sys.executable, "-c", "import sys; from doedesign.cli import main; sys.exit(main())",
                           *map(str, args)], cwd=cwd, preexec_fn=limit, capture_output=True, text=True, timeout=300,
                          env={"PATH": "/usr/bin:/bin", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"})


def _refused(proc, out, *words):
    """Exit 2, one line on stderr naming the process limit and a size, nothing on stdout or in ``out``."""
    err = proc.stderr.strip()
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and len(err.splitlines()) == 1, err
    assert "RLIMIT_AS" in err and " GB" in err, err
    for word in words:
        assert word in err, err
    assert proc.stdout == ""
    assert not out.exists()


def _design(path, n, window=64, levels=True):
    yy, xx = np.mgrid[:n, :n]
    lv = ((xx // 4 + yy // 4) % 16).astype(np.int16) if levels else None
    h = np.zeros((n, n)) if lv is None else -lv * STEP
    cam = Camera(aperture_diameter_m=n * PITCH, window_shape=(window, window), axis_pixel=(window // 2, window // 2))
    Design(h, PITCH, levels=lv, metadata={"name": "d", "camera": cam.to_dict()}).save(path)
    return path


def test_the_budget_counts_the_address_space_limit():
    """In-process: the room under RLIMIT_AS is the soft limit less VmSize (the analytic room)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    cap = budget._status_kb("VmSize") + 2 * 10 ** 9  # 2 GB of room: below any machine's available memory here
    try:
        resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
        (room, name), = [r for r in budget.process_limits() if r[1].startswith("RLIMIT_AS")]
        mapped = budget._status_kb("VmSize")
        assert abs(room - (cap - mapped)) < 64 * 2 ** 20  # pages mapped between the two reads
        assert 1.9e9 < room < 2.01e9
        assert budget.memory_limit_bytes() <= budget.SHARE * room + 1
        with pytest.raises(Exception, match="RLIMIT_AS"):
            budget.check_memory(int(room), "a test")
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def _big_design(path, n):
    """A valid design file of n x n zero heights, its height map streamed into the zip (fast deflate)."""
    small = _design(path.with_name("small.npz"), 8, levels=False)
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (n, n)})
    zeros = bytes(8 * n * 64)
    with zipfile.ZipFile(small) as src, zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name in src.namelist():
            if name != "height_m.npy":
                zf.writestr(name, src.read(name))
        with zf.open("height_m.npy", "w", force_zip64=True) as fh:
            fh.write(header.getvalue())
            for _ in range(n // 64):
                fh.write(zeros)
    return path


def test_masks_of_an_8000_px_design(tmp_path):
    design = _big_design(tmp_path / "big.npz", 8000)
    proc = _limited(["masks", design, "--out", tmp_path / "m"], tmp_path)
    _refused(proc, tmp_path / "m", "8000 x 8000")


def test_psf_on_the_largest_window(tmp_path):
    design = _design(tmp_path / "d.npz", 64)
    proc = _limited(["psf", design, "--window", "8192", "--aperture-mm", "0", "--out", tmp_path / "p.npz"], tmp_path)
    _refused(proc, tmp_path / "p.npz", "8192 px window")


def test_design_of_a_large_element(tmp_path):
    proc = _limited(["design", "bayer", "--size", "4000", "--out", tmp_path / "d.npz"], tmp_path)
    _refused(proc, tmp_path / "d.npz", "4000 x 4000 px design")


def test_tolerance_on_a_large_window(tmp_path):
    design = _design(tmp_path / "d.npz", 64, window=8192)
    proc = _limited(["tolerance", design, "--samples", "2", "--workers", "1", "--wavelengths", "400:700:10",
                     "--out", tmp_path / "t"], tmp_path)
    _refused(proc, tmp_path / "t", "one tolerance sample", "31 wavelengths")


@pytest.fixture(scope="module")
def large_field(tmp_path_factory):
    """A 6000 x 6000 px height map (a real field size of a stitched scan) and its design."""
    tmp = tmp_path_factory.mktemp("field")
    yy, xx = np.mgrid[:6000, :6000]
    height = -(((xx // 30 + yy // 30) % 16) * STEP).astype(np.float32)
    np.savez(tmp / "field.npz", height_m=height, pixel_size_m=np.float64(1e-6))
    return _design(tmp / "d.npz", 64), tmp / "field.npz"


def test_compare_of_a_large_field(large_field, tmp_path):
    design, field = large_field
    proc = _limited(["compare", field, "--design", design, "--out", tmp_path / "c", "--no-psf"], tmp_path)
    _refused(proc, tmp_path / "c", "6000 x 6000 px field")


def test_diagnose_of_a_large_field(large_field, tmp_path):
    design, field = large_field
    proc = _limited(["diagnose", "--measured", field, "--design", design, "--out", tmp_path / "g"], tmp_path)
    _refused(proc, tmp_path / "g", "6000 x 6000 px field")


def test_an_unforeseen_memory_error_is_one_line(tmp_path):
    """A MemoryError past every estimate (here: asked directly of numpy under the limit) is one line."""
    code = ("import sys, numpy as np\n"
            "from doedesign import cli\n"
            "def boom(args):\n"
            "    np.ones((40000, 40000))\n"
            "cli.build_parser = (lambda real: lambda argv=None: (lambda p: (p._subparsers._group_actions[0]"
            ".choices['psf'].set_defaults(func=boom), p)[1])(real(argv)))(cli.build_parser)\n"
            "sys.exit(cli.main(['psf', 'x', '--out', 'y.npz']))\n")

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (LIMIT, LIMIT))

    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, preexec_fn=limit, capture_output=True,
                          text=True, timeout=120)
    err = proc.stderr.strip()
    assert proc.returncode == 2 and "Traceback" not in err and len(err.splitlines()) == 1, err
    assert err.startswith("doe psf: error: out of memory") and "12.8 GB" in err and "40000 x 40000" in err
    assert "RLIMIT_AS" in err
