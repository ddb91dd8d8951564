"""Every option of every command: ranges, types and NaN refused as one line (exit 2), before work.

The parser sweep walks all subcommands (entry points included) so an option added later
without a range is caught here, not by a user.
"""

import argparse
import math
import os

import numpy as np
import pytest

from doedesign.cli import build_parser, main
from doedesign.cli.common import Number, NumberList
from doedesign.design import Design


def _subparsers(parser, prefix=()):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield prefix + (name,), sub
                yield from _subparsers(sub, prefix + (name,))


def _numeric_options():
    out = []
    for path, sub in _subparsers(build_parser()):
        for action in sub._actions:
            if action.option_strings and action.type is not None:
                out.append((" ".join(path), action.option_strings[-1], action.type))
    return out


OPTIONS = _numeric_options()


def test_no_numeric_option_uses_a_bare_int_or_float():
    bare = [(cmd, opt) for cmd, opt, typ in OPTIONS if typ in (int, float)]
    assert not bare, f"options without a range check: {bare}"
    assert len([o for o in OPTIONS if isinstance(o[2], (Number, NumberList))]) >= 25


@pytest.mark.parametrize("cmd,opt,typ", [o for o in OPTIONS if isinstance(o[2], (Number, NumberList))],
                         ids=[f"{c}{o}" for c, o, t in OPTIONS if isinstance(t, (Number, NumberList))])
@pytest.mark.parametrize("text", ["nan", "-inf", "1e400x", "", "1e300", "-1e300"])
def test_every_numeric_option_refuses_nonsense(cmd, opt, typ, text):
    item = typ.item if isinstance(typ, NumberList) else typ
    if text in ("1e300",) and item.hi is None:
        pytest.skip("no upper bound for this option")
    if text == "1e300" and item.allow_inf:
        pytest.skip("inf-like values allowed")
    if text == "-1e300" and item.lo is None:
        pytest.skip("no lower bound")
    with pytest.raises(argparse.ArgumentTypeError):
        typ(text)


def _design(tmp_path, n=16):
    d = Design(np.zeros((n, n)), 5.4e-6, metadata={"name": "flat"})
    return str(d.save(tmp_path / "flat.npz"))


CASES = [
    (["design", "bayer", "--size", "0"], ">= 8"),
    (["design", "bayer", "--size", "-3"], ">= 8"),
    (["design", "bayer", "--iterations", "0"], ">= 1"),
    (["design", "bayer", "--time-limit", "nan"], "'nan'"),
    (["compare", "{m}", "--design", "{d}", "--pixel-size-um", "0"], "> 0"),
    (["compare", "{m}", "--design", "{d}", "--psf-oversample", "0"], ">= 1"),
    (["diagnose", "--design", "{d}", "--measured", "{m}", "--threshold", "nan"], "'nan'"),
    (["diagnose", "--design", "{d}", "--measured", "{m}", "--depths-nm", "75,nan,300,600"], "'nan'"),
    (["psf", "{d}", "--window", "100000"], "8192"),
    (["psf", "{d}", "--window", "0"], ">= 8"),
    (["psf", "{d}", "--depth-m", "abc"], "'abc'"),
    (["psf", "{d}", "--wavelengths-nm", "400:700:1e-12"], "at most 1000"),
    (["psf", "{d}", "--wavelengths-nm", "400:700:nan"], "400:700:nan"),
    (["psf", "{d}", "--wavelengths-nm", "632.8e-9"], "100..20000 nm"),
    (["psf", "{d}", "--aperture-mm", "nan"], "'nan'"),
    (["masks", "{d}", "--clear-aperture-mm", "0"], "> 0"),
    (["calibrate", "psf", "--captures", "x", "--pixel-pitch-um", "0"], "> 0"),
    (["calibrate", "psf", "--captures", "{d}", "--window", "100000,100000"], "8..8192"),
    (["demo", "--doe-px", "0"], ">= 16"),
    (["inspect", "{d}", "--pixel-size-m", "inf"], "'inf'"),
]


@pytest.mark.parametrize("argv,match", CASES, ids=[" ".join(c[0][:1] + c[0][-2:]) for c in CASES])
def test_cli_refuses_bad_option_in_one_line(tmp_path, capsys, argv, match):
    d = _design(tmp_path)
    argv = [a.format(d=d, m=d) for a in argv]
    if "--out" not in argv and argv[0] not in ("inspect",):
        argv += ["--out", str(tmp_path / "out")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert match in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_output_targets_refused_before_work(tmp_path, capsys):
    d = _design(tmp_path)
    (tmp_path / "file").write_text("x")
    (tmp_path / "taken.npz").mkdir()
    for argv, match in ((["masks", d, "--out", str(tmp_path / "file")], "existing file"),
                        (["psf", d, "--out", str(tmp_path / "taken.npz")], "existing folder"),
                        (["design", "bayer", "--out", str(tmp_path / "taken.npz")], "existing folder"),
                        (["design", "bayer", "--out", str(tmp_path / "file" / "d.npz")], "existing file"),
                        (["compare", d, "--design", d, "--out", str(tmp_path / "file")], "existing file")):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert match in err and "Traceback" not in err and err.count("\n") == 1, err


def test_named_pipe_input_refused_not_hung(tmp_path, capsys):
    pipe = tmp_path / "pipe.npz"
    os.mkfifo(pipe)
    for argv in (["inspect", str(pipe)], ["masks", str(pipe), "--out", str(tmp_path / "o")],
                 ["psf", str(pipe), "--out", str(tmp_path / "p.npz")]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "not a regular file" in err and "Traceback" not in err


def test_zero_is_a_value_not_a_default():
    assert Number(int, 0)("0") == 0
    assert math.isinf(Number(float, 0, lo_open=True, allow_inf=True)("inf"))


ONE_LINE_CASES = [
    (["calibrate", "psf", "--captures", "{d}", "--window", "0,0"], "--window '0,0': each must lie in 8..8192"),
    (["calibrate", "psf", "--captures", "{d}", "--window", "4,512"], "8..8192"),
    (["calibrate", "psf", "--captures", "{d}", "--orders", "a"], "--orders must be integers"),
    (["calibrate", "psf", "--captures", "{d}", "--orders", "0,1,100000"], "each must lie in -1000..1000"),
    (["diagnose", "--design", "{d}", "--measured", "{m}", "--effects", ","], "names no effect"),
    (["diagnose", "--design", "{d}", "--measured", "{m}", "--effects", ""], "names no effect"),
    (["diagnose", "--design", "{d}", "--measured", "{m}", "--effects", "mask_overlay,nope"], "unknown effect 'nope'"),
    (["diagnose", "--design", "{d}", "--measured-psf", "{m}", "--effects", "mask_overlay"],
     "belongs to the height domain"),
]


@pytest.mark.parametrize("argv,match", ONE_LINE_CASES, ids=[" ".join(c[0][:1] + c[0][-2:]) for c in ONE_LINE_CASES])
def test_cli_refuses_bad_value_in_one_line_before_work(tmp_path, capsys, argv, match):
    d = _design(tmp_path)
    out = tmp_path / "out"
    argv = [a.format(d=d, m=d) for a in argv] + ["--out", str(out)]
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert match in captured.err and captured.err.count("\n") == 1 and "Traceback" not in captured.err, captured.err
    assert not captured.out and not out.exists()


def test_camera_entry_errors_name_the_design_file(tmp_path, capsys):
    import json

    path = tmp_path / "badcam.npz"
    d = Design(np.zeros((16, 16)), 5.4e-6, metadata={"name": "internal-name", "camera": {"pixel_pitch_m": -1.0}})
    np.savez(path, height_m=d.height_m, pitch_m=np.float64(d.pitch_m), material=np.str_(d.material),
             design_wavelength_m=np.float64(d.design_wavelength_m), metadata=np.str_(json.dumps(d.metadata)))
    stack = tmp_path / "stack.npz"
    np.savez(stack, psf=np.ones((2, 1, 16, 16)), wavelengths_m=np.array([550e-9]), pixel_pitch_m=np.float64(5.4e-6),
             views=np.array(["coded", "uncoded"]))
    out = tmp_path / "out"
    assert main(["diagnose", "--design", str(path), "--measured-psf", str(stack), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"doe diagnose: error: {path}: metadata camera") and err.count("\n") == 1, err
    assert "internal-name" not in err and not out.exists()


@pytest.mark.parametrize("text,match", [("a = " + "[" * 50_000 + "]" * 50_000 + "\n", "nested too deeply"),
                                        ("a = " + "9" * 5000 + "\n", "not valid TOML")])
def test_hostile_toml_is_one_line(tmp_path, capsys, text, match):
    from doedesign import targets
    from doedesign.errors import DoeError

    path = tmp_path / "hostile.toml"
    path.write_text(text)
    with pytest.raises(DoeError, match=match):
        targets.load_toml(path)
    out = tmp_path / "out.npz"
    for argv in (["design", "bayer", "--config", str(path), "--out", str(out)],
                 ["design", str(path), "--out", str(out)]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and str(path) in err and match in err and "Traceback" not in err, err
    assert not out.exists()
