"""The Bayer colour-sorting study (seed supplement section 2, Table 1)."""

import json

import numpy as np
import pytest

from doedesign import bayer, cli
from doedesign.camera import Camera
from doedesign.design import Design


@pytest.fixture(scope="module")
def images():
    return bayer.load_images(crop=128)


def test_nearest_and_bilinear_are_exact_on_flat_colour():
    img = np.broadcast_to([0.2, 0.5, 0.8], (16, 16, 3)).copy()
    rng = np.random.default_rng(0)
    for rec in (bayer.nearest_neighbour, bayer.bilinear_demosaic):
        raw = bayer.mosaic(img, rng, sigma=0.0)
        np.testing.assert_allclose(rec(raw), img, atol=1e-12)


def test_target_psf_samples_one_scene_point_per_cell():
    # With the Eq. (1) PSF and no noise, every pixel of a 2 x 2 cell gets the scene's R, G, B
    # at the cell's top-left pixel: the three samples come from the same point.
    rng = np.random.default_rng(1)
    img = rng.uniform(0, 1, (12, 12, 3))
    kern = bayer.delta_kernels(bayer.TARGET_OFFSETS)
    rec = bayer.nearest_neighbour(bayer.mosaic(bayer.apply_psf(img, kern), rng, sigma=0.0))
    expect = np.repeat(np.repeat(img[0::2, 0::2], 2, axis=0), 2, axis=1)
    np.testing.assert_allclose(rec[2:, 2:], expect[2:, 2:], atol=1e-12)
    ideal = bayer.nearest_neighbour(bayer.mosaic(img, rng, sigma=0.0))
    assert np.abs(ideal[2:, 2:] - expect[2:, 2:]).max() > 0.1


def test_noise_is_sigma_one_on_255_scale():
    rng = np.random.default_rng(2)
    raw = bayer.mosaic(np.full((200, 200, 3), 0.5), rng)
    assert np.std(raw) * 255 == pytest.approx(1.0, rel=0.03)


def test_proposed_target_improves_chroma_like_table1(images):
    table, per_image, _ = bayer.evaluate(images, bayer.standard_methods())
    ideal, prop = table["ideal_nearest"], table["proposed_target"]
    # Paper: U +1.9 dB, V +2.1 dB, RGB unchanged, L slightly lower.
    assert prop["u_db"] - ideal["u_db"] >= 1.0
    assert prop["v_db"] - ideal["v_db"] >= 1.0
    assert abs(prop["rgb_db"] - ideal["rgb_db"]) < 0.5
    assert prop["l_db"] < ideal["l_db"]
    for name in images:
        assert per_image["proposed_target"][name]["u_db"] > per_image["ideal_nearest"][name]["u_db"]
    # Bilinear demosaicing beats cell-wise nearest neighbour on luminance for the ideal PSF.
    assert table["ideal_demosaic"]["l_db"] > ideal["l_db"]


def test_psnr_definition():
    ref = np.full((20, 20, 3), 0.5)
    est = ref + 0.01
    assert bayer.psnr_scores(ref, est)["rgb_db"] == pytest.approx(40.0, abs=1e-9)
    assert bayer.psnr_scores(ref, ref)["u_db"] == float("inf")


def test_cli_evaluate_bayer(tmp_path, capsys):
    cam = Camera(aperture_diameter_m=32 * 5.4e-6)
    design = Design(np.zeros((32, 32)), 5.4e-6, metadata={"camera": cam.to_dict(), "name": "flat"})
    design.save(tmp_path / "flat.npz")
    out = tmp_path / "study"
    code = cli.main(["evaluate-bayer", "--design", str(tmp_path / "flat.npz"), "--out", str(out),
                     "--crop", "64", "--images", "astronaut,coffee"])
    assert code == 0
    table = json.loads((out / "table.json").read_text())
    for row in ("ideal_demosaic", "ideal_nearest", "proposed_target", "proposed_doe"):
        assert set(table[row]) == {"rgb_db", "l_db", "u_db", "v_db"}
    assert "paper" in table["notes"]
    # A flat DOE only blurs (no colour sorting): no chroma gain over the ideal PSF.
    assert table["proposed_doe"]["u_db"] < table["proposed_target"]["u_db"]
    assert (out / "fig2.png").stat().st_size > 1000
    # The Pareto front of the weight sweep, with the bounds, beside the chosen design.
    assert (out / "front.png").stat().st_size > 1000
    front = table["pareto_front"]
    assert len(front) == 7 and all(len(p["quantized"]) == 3 for p in front)
    bound = table["doe"]["bound"]
    assert all(e <= b + 1e-9 for e, b in zip(bound["energy"][0], bound["bound"][0]))
    assert all(max(p["continuous"][c] for p in front) <= bound["bound"][0][c] + 1e-6 for c in range(3))
    capsys.readouterr()
    assert cli.main(["evaluate-bayer", "--no-doe", "--images", "nosuchimage", "--out", str(tmp_path / "bad")]) == 2
    assert "nosuchimage" in capsys.readouterr().err
    assert not (tmp_path / "bad" / "table.json").exists()
