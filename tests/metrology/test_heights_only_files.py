"""A heights-only design (continuous heights, phase wrapped at 2 pi, no ``levels``) is judged
against the levels ``doe masks`` prints from it, in `doe compare` and in `doe diagnose`.

The wafer is the generator's (tests/metrology/filegen.py) perfect print of those levels
(``doedesign.levels.design_levels``, the function ``doe masks`` uses), so the comparison must
see nothing but the instrument: interior errors at the noise, no fabrication effect named.
Judged against the continuous heights instead, the quantization (+-step/2) and the wrap
(15.6 steps deep printed as level 0, a 1.17 um difference) would show as errors.
"""

import json

import numpy as np
import pytest
import scipy.ndimage as ndi

import filegen
from doedesign.cli import main
from doedesign.design import Design
from doedesign.levels import design_levels
from metrology.formats.writers import write_datx


@pytest.fixture(scope="module")
def heights_only(tmp_path_factory):
    """A smooth phase plus a ramp and an unetched disc, wrapped into (-2 pi, 0], as heights."""
    tmp = tmp_path_factory.mktemp("heights_only")
    rng = np.random.default_rng(21)
    shape = (40, 40)
    phase = ndi.gaussian_filter(rng.standard_normal(shape), 3.0, mode="wrap")
    phase = phase * 2.5 / phase.std() + np.arange(shape[1])[None, :] / 6.0
    rr, cc = np.mgrid[:shape[0], :shape[1]]
    phase[np.hypot(rr - 22, cc - 17) < 6] = 0.0
    probe = Design(height_m=np.zeros(shape), pitch_m=filegen.PITCH_M)
    height = -np.mod(phase, 2 * np.pi) / (2 * np.pi) * probe.height_2pi_m()
    design = Design(height_m=height, pitch_m=filegen.PITCH_M, metadata={"name": "heights_only"})
    levels = design_levels(design)
    step = design.level_step_m()
    wrapped = np.count_nonzero((levels == 0) & (height < -8 * step))
    assert wrapped > 10  # some pixels print as level 0 although 15.5-16 steps deep
    case = filegen.make_case([], 21, levels=levels, field_px=130, fine=40)
    d_path, m_path = tmp / "design.npz", tmp / "measured.datx"
    design.save(d_path)
    assert Design.load(d_path).levels is None
    write_datx(m_path, case.height_m, case.instrument["header_pixel_m"])
    return {"design": d_path, "measured": m_path, "case": case, "tmp": tmp, "height": height, "levels": levels}


def test_compare_judges_the_printed_levels(heights_only):
    out = heights_only["tmp"] / "cmp"
    assert main(["compare", str(heights_only["measured"]), "--design", str(heights_only["design"]), "--out", str(out),
                 "--no-psf", "--no-render"]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["match"]["confidence"] == "high"
    # The generator etches 75 nm * 2**j against the design's 74.74 nm steps (up to 3.9 nm at level 15)
    # over 0.5-1.5 nm of noise: a few nm. Against the continuous heights it would be tens of nm.
    assert rep["height_error_interior_rms_nm"] < 4.0
    levels, height = heights_only["levels"], heights_only["height"]
    quantization = np.sqrt(np.mean((height + levels * Design(height_m=height, pitch_m=5.4e-6).level_step_m()) ** 2))
    assert quantization * 1e9 > 5 * 4.0


@pytest.mark.slow
def test_diagnose_names_nothing_on_a_perfect_print(heights_only):
    out = heights_only["tmp"] / "diag"
    assert main(["diagnose", "--measured", str(heights_only["measured"]), "--design", str(heights_only["design"]),
                 "--out", str(out)]) == 0
    rep = json.loads((out / "report.json").read_text())
    fab = [s["effect"] for s in rep["steps"] if not s["measurement_artefact"]]
    assert fab == []
    assert rep["final_residual_rms"] < 1.3 * rep["noise_floor"]
