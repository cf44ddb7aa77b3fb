"""What the library writes: every method's output reads back without repair (the output policy,
`jaxdenoise.inference.OUTPUT_POLICY`), PNG/JPEG outputs carry the sRGB curve, and the CLI refuses an
output it cannot write before anything runs."""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

import jaxdenoise as jd
from jaxdenoise import cli
from jaxdenoise.color import inv_srgb, srgb
from jaxdenoise.inference import nonnegative
from jaxdenoise.io import ExrError, read_buffers, write_display, write_image
from jaxdenoise.methods import available, get

GOLDEN = Path(__file__).resolve().parent / "data" / "golden" / "spp0004_00.exr"  # every buffer, dx/dy too


def test_nonnegative_counts_pixels_and_leaves_a_valid_image_alone():
    img = np.ones((4, 5, 3), np.float32)
    same, n = nonnegative(img)
    assert n == 0 and np.array_equal(same, img)
    img[1, 2] = (-1.0, 0.5, -2.0)  # one pixel, two negative samples
    img[3, 4, 1] = -1e-9
    out, n = nonnegative(img)
    assert n == 2 and out.min() == 0.0
    assert out[1, 2].tolist() == [0.0, 0.5, 0.0] and out[0, 0].tolist() == [1.0, 1.0, 1.0]


# The networks and the cross filters compile for 10-25 s each: they run in the slow set (the
# networks' outputs are also checked finite and scored by tests/test_golden.py in the default run;
# the cross filters are normalised weighted means of non-negative radiance).
NETWORKS = {"lbf", "lbf-nlm", "demc", "rae", "gradnet", "bilateral", "nlm"}


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in NETWORKS else n
                                  for n, why in available().items() if why is None])
def test_every_method_output_reads_back_without_repair(name, tmp_path):
    buffers, _ = read_buffers(GOLDEN)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        image = jd.denoise(buffers, name)
    assert image.dtype == np.float32 and image.shape == (64, 64, 3)
    assert np.all(np.isfinite(image)) and image.min() >= 0.0
    out = write_image(tmp_path / "out.exr", image)
    again, _ = read_buffers(out)  # repair=None: any negative or NaN sample would raise
    np.testing.assert_array_equal(again.color, image)  # float32 EXR: exact
    clamps = [w for w in caught if "negative radiance" in str(w.message)]
    assert len(clamps) <= 1  # at most one warning per call


def test_poisson_clamp_is_counted_in_api_cli_and_bench(tmp_path):
    buffers, _ = read_buffers(GOLDEN)
    with pytest.warns(jd.JaxdenoiseWarning, match=r"poisson-l2: \d+ pixel\(s\) .* negative radiance"):
        image = jd.denoise(buffers, "poisson-l2")
    m = get("poisson-l2")
    raw = np.asarray(m.module.apply({}, buffers, m.config))  # the method's own output, unclamped
    expected = int((raw < 0).any(axis=-1).sum())
    assert expected > 0, "the golden frame no longer makes the L2 solve overshoot: pick a frame that does"
    np.testing.assert_array_equal(image, np.maximum(raw, 0))
    out = tmp_path / "p.exr"
    assert cli.main(["denoise", str(GOLDEN), "-o", str(out), "--method", "poisson-l2"]) == 0
    _, attrs = read_buffers(out)
    assert attrs["jaxdenoise:negative_clamped"] == expected
    assert json.loads(out.with_name("p.config.json").read_text())["negative_clamped"] == expected


def test_png_has_the_srgb_curve_and_the_exposure(tmp_path):
    import OpenImageIO as oiio

    linear = np.array([0.0, 0.0031308, 0.05, 0.2140, 0.5, 1.0, 4.0], np.float32)
    image = np.repeat(linear[None, :, None], 3, axis=2)
    for exposure in (0.0, -2.0):
        path = write_display(tmp_path / f"e{exposure}.png", image, exposure=exposure)
        inp = oiio.ImageInput.open(str(path))
        got = inp.read_image(0, 0, 0, 3, "uint8")
        inp.close()
        want = np.round(np.asarray(srgb(np.clip(linear * 2.0 ** exposure, 0, 1))) * 255)
        np.testing.assert_array_equal(got[0, :, 0], want.astype(np.uint8))  # exact: the same rounding
    # the curve itself, against IEC 61966-2-1's published values (tolerance 1e-4 absolute)
    assert float(srgb(0.2140)) == pytest.approx(0.5, abs=1e-3)  # mid-grey 128/255 = 0.502
    assert float(srgb(0.0031308)) == pytest.approx(0.04045, abs=1e-4)
    np.testing.assert_allclose(np.asarray(inv_srgb(srgb(linear[:-1]))), linear[:-1], rtol=1e-5, atol=1e-7)


def test_cli_writes_png_tone_mapped_and_refuses_other_formats_before_running(tmp_path, capsys, monkeypatch):
    import OpenImageIO as oiio

    out = tmp_path / "o.png"
    assert cli.main(["denoise", str(GOLDEN), "-o", str(out), "--method", "gaussian", "--exposure", "1"]) == 0
    inp = oiio.ImageInput.open(str(out))
    png = inp.read_image(0, 0, 0, 3, "uint8")
    inp.close()
    exr = tmp_path / "o.exr"
    assert cli.main(["denoise", str(GOLDEN), "-o", str(exr), "--method", "gaussian"]) == 0
    linear = read_buffers(exr)[0].color
    want = np.round(np.asarray(srgb(np.clip(linear * 2.0, 0, 1))) * 255).astype(np.uint8)
    np.testing.assert_array_equal(png, want)

    from jaxdenoise import inference

    monkeypatch.setattr(inference, "inference_fn", lambda m: pytest.fail("ran before refusing the output"))
    for bad, why in ((["-o", str(tmp_path / "o.tif")], "unknown output format '.tif'"),
                     (["-o", str(exr), "--exposure", "1"], "--exposure applies to a PNG/JPEG output")):
        with pytest.raises(SystemExit, match=why):
            cli.main(["denoise", str(GOLDEN), "--method", "gaussian", *bad])
    with pytest.raises(ExrError, match="write_image writes linear HDR EXR"):
        write_image(tmp_path / "x.png", linear)
