"""Directly seen emission kept out of dx, dy (issue 37, item 4; Kettunen et al. 2015's tracer).

With ``direct_emission="separate"`` (data_gen's default) a gradient frame's ``dx``/``dy`` are the
finite differences of ``color - emission``, ``emission`` being what surface emitters seen directly
give each pixel; every reconstruction solves for ``color - emission`` and adds it back. Checked
here: unbiasedness with a light in view (both shifts, the G-PT tests' z-scores), the data contract
(EXR layer, header, `Buffers.only`), and the reconstructions' bookkeeping.
"""
from __future__ import annotations

import numpy as np
import pytest

from jaxdenoise.buffers import Buffers

mitsuba = pytest.mark.mitsuba
RES = 16


def _cornell(res: int = RES):
    from data_gen.mitsuba_setup import setup_mitsuba

    setup_mitsuba()
    import mitsuba as mi

    d = mi.cornell_box()
    d["sensor"]["film"].update({"width": res, "height": res, "rfilter": {"type": "box"}})
    return mi.load_dict(d)


@pytest.fixture(scope="module")
def cornell():
    from data_gen.integrator import PathSettings
    from data_gen.render import render_buffers

    scene = _cornell()
    return scene, render_buffers(scene, spp=8192, seed=987654, settings=PathSettings())


def _z(d, v):
    from tests.test_gpt import _z_scores

    return float(_z_scores(d, v).max())


@mitsuba
@pytest.mark.parametrize("shift", ["reconnect", "replay"])
def test_separate_emission_is_unbiased_with_a_light_in_view(cornell, shift):
    """dx + grad(emission) and dy + grad(emission) match the reference's differences, and the primal
    the reference (|z| < 5; measured max 3.6); dy alone does not (the ceiling light's edges are
    left out: a pixel's |z| is about 100), so the separation is real and the statistic sees it. The
    emission image is the light where the light is seen and 0 elsewhere."""
    from data_gen.gradient import render_gradients

    scene, ref = cornell
    r, rv = ref["color"], ref["color_var"]
    g = render_gradients(scene, spp=256, seed=0, shift=shift, primal="gpt" if shift == "reconnect" else "base")
    e, ev = g["emission"], g["emission_var"]
    assert e.max() > 1.0 and (e == 0).mean() > 0.8  # the light covers a few percent of the frame
    zx = _z(g["dx"][:, :-1] + e[:, 1:] - e[:, :-1] - (r[:, 1:] - r[:, :-1]),
            g["dx_var"][:, :-1] + ev[:, 1:] + ev[:, :-1] + rv[:, 1:] + rv[:, :-1])
    zy = _z(g["dy"][:-1] + e[1:] - e[:-1] - (r[1:] - r[:-1]), g["dy_var"][:-1] + ev[1:] + ev[:-1] + rv[1:] + rv[:-1])
    zp = _z(g["primal"] - r, g["primal_var"] + rv)
    assert max(zx, zy, zp) < 5.0, (zx, zy, zp)
    # per pixel: the light is one row at this size, so a block sum of dy telescopes over its edges
    blind = np.abs(g["dy"][:-1] - (r[1:] - r[:-1])) / np.sqrt(g["dy_var"][:-1] + rv[1:] + rv[:-1] + 1e-30)
    assert blind.max() > 5.0, blind.max()
    assert g["n_invalid"] == 0


@mitsuba
def test_included_emission_keeps_the_old_gradients(cornell):
    """``direct_emission="included"`` returns no emission image and gradients of the whole colour
    (|z| < 5 against the reference's differences); the base image is the same in both modes."""
    from data_gen.gradient import render_gradients

    scene, ref = cornell
    r, rv = ref["color"], ref["color_var"]
    g = render_gradients(scene, spp=256, seed=0, direct_emission="included")
    assert "emission" not in g
    zy = _z(g["dy"][:-1] - (r[1:] - r[:-1]), g["dy_var"][:-1] + rv[1:] + rv[:-1])
    assert zy < 5.0, zy
    sep = render_gradients(scene, spp=256, seed=0)
    assert np.array_equal(sep["primal"], g["primal"])  # tolerance: bit-identical (same base paths)
    with pytest.raises(ValueError, match="direct_emission"):
        render_gradients(scene, spp=2, direct_emission="both")


@mitsuba
def test_shot_writes_the_emission_layer_and_header(tmp_path):
    """`render_shot` writes the ``emission`` layer beside dx, dy with ``gradient_emission`` in the
    header and the resume key; ``included`` writes no layer and re-renders the frame."""
    from data_gen.shot import render_shot
    from jaxdenoise.io import read_buffers

    scene = _cornell(8)
    rec = render_shot(scene, tmp_path, spp=[2], ref_spp=0, methods=["poisson-l2"], progress=False)
    entry = rec["files"]["spp0002_00.exr"]
    assert entry["key"]["gradient_emission"] == "separate" and "emission" in entry["fields"]
    frame, attrs = read_buffers(tmp_path / "spp0002_00.exr")
    assert attrs["gradient_emission"] == "separate" and frame.emission is not None and frame.emission.max() > 1.0
    render_shot(scene, tmp_path, spp=[2], ref_spp=0, methods=["poisson-l2"], gradient_emission="included",
                progress=False)
    frame, attrs = read_buffers(tmp_path / "spp0002_00.exr")
    assert attrs["gradient_emission"] == "included" and frame.emission is None and frame.dx is not None


def _frame(h=9, w=11, seed=0):
    rng = np.random.default_rng(seed)
    clean = rng.uniform(0.1, 2.0, (h, w, 3)).astype(np.float32)
    emission = np.where(rng.random((h, w, 1)) < 0.2, rng.uniform(5.0, 20.0, (h, w, 3)), 0.0).astype(np.float32)
    rest = clean  # the part the gradients describe
    dx = np.zeros_like(rest)
    dx[:, :-1] = rest[:, 1:] - rest[:, :-1]
    dy = np.zeros_like(rest)
    dy[:-1] = rest[1:] - rest[:-1]
    return Buffers(color=rest + emission, dx=dx, dy=dy, emission=emission, spp=np.float32(64))


@pytest.mark.parametrize("name", ["poisson-l2", "poisson-l1"])
def test_poisson_solves_without_the_emission_and_adds_it_back(name):
    """Exact gradients of ``color - emission`` with that colour as the base: the reconstruction returns
    the colour, emission included (Poisson's identity; tolerance 1e-4 relative, float32 solves); read
    as if the gradients held the emission (the layer dropped), it does not (the light's edges are
    then missing from the gradients: off by more than 10 %)."""
    import jaxdenoise

    b = _frame()
    out = np.asarray(jaxdenoise.denoise(b, name))
    np.testing.assert_allclose(out, b.color, rtol=1e-4, atol=1e-4)
    wrong = np.asarray(jaxdenoise.denoise(b.replace(emission=None), name))
    assert np.abs(wrong - b.color).max() > 0.1 * float(b.emission.max())


def test_gradnet_reconstructs_color_minus_emission_and_adds_it_back():
    """GradNet (shipped weights) on a frame with an emission layer equals GradNet on ``color -
    emission`` without one, plus the emission (tolerance 1e-5 absolute: the same program)."""
    import jaxdenoise

    rng = np.random.default_rng(3)
    b = _frame(16, 16)
    feats = dict(albedo=rng.uniform(0, 1, (16, 16, 3)).astype(np.float32),
                 normal=rng.uniform(-1, 1, (16, 16, 3)).astype(np.float32),
                 depth=rng.uniform(1, 3, (16, 16, 1)).astype(np.float32))
    b = b.replace(**feats)
    with_layer = np.asarray(jaxdenoise.denoise(b, "gradnet"))
    without = np.asarray(jaxdenoise.denoise(b.replace(color=b.color - b.emission, emission=None), "gradnet"))
    np.testing.assert_allclose(with_layer, without + b.emission, atol=1e-5, rtol=1e-5)


def test_only_keeps_the_emission_with_the_gradients():
    b = _frame()
    assert b.only({"dx", "dy"}).emission is not None
    assert b.only({"albedo"}).emission is None


def test_exr_round_trip_and_header_checks(tmp_path):
    """The layer is ``emission.R/G/B``; a header that says ``separate`` without the layer, or
    ``included`` with one, is refused with the file and the channels named."""
    from jaxdenoise.io import ExrError, read_buffers, write_buffers

    b = _frame()
    p = write_buffers(tmp_path / "a.exr", b, {"gradient_emission": "separate"})
    back, attrs = read_buffers(p)
    np.testing.assert_array_equal(back.emission, b.emission)
    p = write_buffers(tmp_path / "b.exr", b.replace(emission=None), {"gradient_emission": "separate"})
    with pytest.raises(ExrError, match=r"b\.exr.*emission\.R"):
        read_buffers(p)
    p = write_buffers(tmp_path / "c.exr", b, {"gradient_emission": "included"})
    with pytest.raises(ExrError, match=r"c\.exr.*included"):
        read_buffers(p)
    p = write_buffers(tmp_path / "d.exr", b.replace(emission=None), {})  # a frame from before: no attribute
    assert read_buffers(p)[0].emission is None
