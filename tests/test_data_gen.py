"""data_gen: the buffer integrator, references, scenes, the bench-layout writer and resumability.

All renders are tiny (<= 16x16, few spp). Tests that need Dr.Jit's LLVM backend are marked
``mitsuba`` and fail with the reason when only ``scalar_rgb`` works; the scalar fallback has its own
4x4 test.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import data_gen
from data_gen import integrator, render, scenes, shot


def _llvm() -> str:
    v = data_gen.setup_mitsuba()
    assert v.startswith("llvm"), f"these tests need an LLVM Mitsuba variant; setup_mitsuba() chose {v!r}"
    return v


def _cornell(res=16, max_depth=8):
    import mitsuba as mi

    d = mi.cornell_box()
    d["sensor"]["film"] = {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}
    d["integrator"] = {"type": "path", "max_depth": max_depth}
    return mi.load_dict(d)


def _relmse(x, ref):
    return float(np.mean((x - ref) ** 2 / (ref ** 2 + 0.01)))


def test_setup_mitsuba_is_idempotent_and_avoids_old_llvm():
    v1 = data_gen.setup_mitsuba()
    v2 = data_gen.setup_mitsuba()
    assert v1 == v2
    for path in data_gen.mitsuba_setup.llvm_candidates():
        major = data_gen.mitsuba_setup._llvm_major(path)
        assert major is None or major >= 16, f"candidate {path} is LLVM {major} (< 16 crashes Dr.Jit)"


def test_setup_mitsuba_rejects_unknown_variant():
    data_gen.mitsuba_setup._CHOSEN, saved = None, data_gen.mitsuba_setup._CHOSEN
    try:
        with pytest.raises(ValueError, match="prefer="):
            data_gen.setup_mitsuba("no_such_variant")
    finally:
        data_gen.mitsuba_setup._CHOSEN = saved
        data_gen.setup_mitsuba()


@pytest.mark.mitsuba
def test_variance_of_mean_matches_spread_of_independent_renders():
    _llvm()
    scene = _cornell(12, max_depth=4)
    st = data_gen.PathSettings(max_depth=4)
    runs = [render.render_buffers(scene, spp=16, seed=100 + k, settings=st, record=("normal", "visibility"))
            for k in range(16)]
    for field, var_field in (("color", "color_var"), ("visibility", "visibility_var"), ("normal", "normal_var")):
        means = np.stack([r[field] for r in runs])
        spread = means.var(axis=0, ddof=1)  # (H, W, C): empirical variance of the pixel mean
        if var_field != "color_var":
            spread = spread.mean(-1, keepdims=True)
        predicted = np.mean([r[var_field] for r in runs], axis=0)
        mask = predicted > 1e-8
        ratio = spread[mask].sum() / predicted[mask].sum()
        # 16 renders x ~100+ pixels: the pooled ratio's sampling error is a few percent; 25 % is loose.
        assert 0.75 < ratio < 1.25, f"{field}: spread / predicted variance of the mean = {ratio:.3f} (tol 0.75..1.25)"


@pytest.mark.mitsuba
def test_radiance_agrees_with_mitsuba_path_integrator():
    import mitsuba as mi

    _llvm()
    scene = _cornell(16)
    ours = render.render_buffers(scene, spp=512, seed=3, settings=data_gen.PathSettings(max_depth=8))["color"]
    path_a = np.asarray(mi.render(scene, spp=512, seed=11))
    path_b = np.asarray(mi.render(scene, spp=512, seed=12))
    e_ours, e_path = _relmse(ours, path_a), _relmse(path_b, path_a)
    # Two independent renders with the same variance: RelMSE(ours, path) ~ RelMSE(path, path). A bias
    # or extra variance would raise the ratio; 1.5x is well above the ~10 % sampling error here.
    assert e_ours < 1.5 * e_path, f"RelMSE ours-vs-path {e_ours:.3e} vs path-vs-path {e_path:.3e} (tol 1.5x)"
    assert abs(ours.mean() / path_a.mean() - 1) < 0.02, "image mean differs from Mitsuba path by > 2 %"


@pytest.mark.mitsuba
def test_determinism_for_a_fixed_seed():
    _llvm()
    scene = _cornell(8)
    st = data_gen.PathSettings(max_depth=5)
    a = render.render_buffers(scene, spp=8, seed=5, settings=st, record=data_gen.FEATURES)
    b = render.render_buffers(scene, spp=8, seed=5, settings=st, record=data_gen.FEATURES)
    c = render.render_buffers(scene, spp=8, seed=6, settings=st, record=data_gen.FEATURES)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=f"{k}: same seed gave different values (tol: exact)")
    assert not np.array_equal(a["color"], c["color"]), "different seeds gave identical color"


@pytest.mark.mitsuba
def test_passes_bound_memory_without_changing_the_estimator():
    import mitsuba as mi

    _llvm()
    scene = _cornell(12, max_depth=3)
    st = data_gen.PathSettings(max_depth=3)
    ref = np.asarray(mi.render(scene, spp=1024, seed=9))
    dark = ref.max(-1) < 1.0  # leave out the directly seen light: its edge pixels dominate the noise
    one = render.render_buffers(scene, spp=64, seed=1, settings=st, samples_per_pass=1 << 20)
    many = render.render_buffers(scene, spp=64, seed=1, settings=st, samples_per_pass=144 * 5)  # 5 spp a pass
    for k in ("color", "color_var"):
        assert one[k].shape == many[k].shape == (12, 12, 3)
    for name, out in (("one pass", one), ("13 passes", many)):
        rel = out["color"][dark].mean() / ref[dark].mean() - 1
        # ~8000 samples over the unlit-by-sight pixels: the mean's noise is ~2 %; 10 % flags a broken split.
        assert abs(rel) < 0.1, f"{name}: mean off by {rel:+.1%} from Mitsuba path (tol 10 %)"


@pytest.mark.mitsuba
def test_features_have_documented_ranges_and_miss_values():
    _llvm()
    d = data_gen.default_scene(width=16, height=16)
    s = scenes.load_scene(d)
    out = render.render_buffers(s, spp=4, seed=0, settings=data_gen.PathSettings(), record=data_gen.FEATURES)
    n = np.linalg.norm(out["normal"], axis=-1)
    assert np.all(n <= 1 + 1e-5), "mean normal longer than 1 (tol 1e-5)"
    assert np.all((out["visibility"] >= 0) & (out["visibility"] <= 1)), "visibility outside [0, 1]"
    assert np.mean(out["depth"] > 0) > 0.9, "the room fills the view: > 90 % of pixels must have depth > 0"
    assert np.all((out["roughness"] >= 0) & (out["roughness"] <= 1)), "roughness outside [0, 1]"
    assert out["roughness"].min() < 0.3, "the gold sphere (alpha 0.15) should show in the roughness buffer"
    assert np.all(np.isfinite(np.concatenate([v.reshape(-1) for v in out.values()]))), "non-finite buffer"
    # A scene with nothing but the camera: every ray misses, all features are 0 by definition.
    import mitsuba as mi

    empty = mi.load_dict({"type": "scene", "sensor": {"type": "perspective", "film": {
        "type": "hdrfilm", "width": 4, "height": 4}}})
    out = render.render_buffers(empty, spp=2, seed=0, settings=data_gen.PathSettings(), record=data_gen.FEATURES)
    for k, v in out.items():
        assert np.all(v == 0), f"{k}: expected 0 everywhere for missed rays"


def test_bsdf_roughness_rule():
    data_gen.setup_mitsuba()
    import mitsuba as mi

    assert integrator.bsdf_roughness(mi.load_dict({"type": "diffuse"})) == 1.0
    assert integrator.bsdf_roughness(mi.load_dict({"type": "dielectric"})) == 0.0
    assert integrator.bsdf_roughness(mi.load_dict({"type": "roughconductor", "alpha": 0.2})) == pytest.approx(0.2, abs=1e-6)


def _xml(tmp_path: Path, texture: str | None) -> Path:
    tex = (f'<texture type="bitmap" name="reflectance"><string name="filename" value="{texture}"/></texture>'
           if texture else '<rgb name="reflectance" value="0.5"/>')
    p = tmp_path / "scene.xml"
    p.write_text(f"""<scene version="3.0.0">
  <default name="resx" value="8"/><default name="resy" value="8"/>
  <integrator type="path"><integer name="max_depth" value="4"/></integrator>
  <sensor type="perspective"><float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="$resx"/><integer name="height" value="$resy"/></film>
  </sensor>
  <shape type="rectangle"><bsdf type="diffuse">{tex}</bsdf></shape>
  <emitter type="constant"><rgb name="radiance" value="1.0"/></emitter>
</scene>
""")
    return p


@pytest.mark.mitsuba
def test_xml_scene_renders_into_the_bench_layout(tmp_path):
    from jaxdenoise.io import read_buffers, read_image

    _llvm()
    import OpenImageIO as oiio

    tex = np.random.default_rng(0).random((8, 8, 3)).astype(np.float32)
    buf = oiio.ImageBuf(oiio.ImageSpec(8, 8, 3, oiio.FLOAT))
    buf.set_pixels(oiio.ROI(), tex)
    assert buf.write(str(tmp_path / "tex.exr"))
    xml = _xml(tmp_path, "tex.exr")
    rec = data_gen.render_shot(xml, tmp_path / "shot", spp=(2, 4), ref_spp=8, instances=2, progress=False)
    names = sorted(p.name for p in (tmp_path / "shot").glob("*.exr"))
    assert names == ["reference.exr", "spp0002_00.exr", "spp0002_01.exr", "spp0004_00.exr", "spp0004_01.exr"]
    b, attrs = read_buffers(tmp_path / "shot" / "spp0004_01.exr")
    assert int(attrs["spp"]) == 4 and b.color.shape == (8, 8, 3)
    assert b.albedo is not None and b.normal is not None and b.color_var is not None
    assert b.roughness is None, "all-diffuse scene: a constant roughness buffer is left out"
    assert "roughness" in rec["left_out"]["spp4"] and "dx" in rec["left_out"]["spp4"]
    ref = read_image(tmp_path / "shot" / "reference.exr")
    assert ref.shape == (8, 8, 3) and np.isfinite(rec["reference"]["relmse_halves"])
    for name, entry in rec["files"].items():
        assert entry["sha256"] == shot.sha256(tmp_path / "shot" / name)
        # render time and one-off kernel compilation are recorded apart (both >= 0)
        assert entry["seconds"] >= 0 and entry["compile_seconds"] >= 0


@pytest.mark.mitsuba
def test_render_timer_takes_kernel_compilation_out():
    """A kernel Dr.Jit has never seen (a literal unique to this run makes its hash new, so neither
    the in-memory nor the on-disk cache has it) is charged to compile_seconds, not to seconds; the
    same kernel again compiles nothing. Tolerance: the two parts add up to the wall time within 5 ms
    (the timer's own bookkeeping)."""
    import time

    import drjit as dr
    import mitsuba as mi

    from data_gen.mitsuba_setup import RenderTimer

    _llvm()
    salt = 1.0 + (time.time_ns() % 1_000_003) * 1e-7

    def work():
        x = dr.arange(mi.Float, 4096) * salt
        y = dr.sin(x) * dr.cos(x * salt) + dr.sqrt(x + salt)
        dr.eval(y)

    t0 = time.perf_counter()
    with RenderTimer() as first:
        work()
    wall = time.perf_counter() - t0
    assert first.compile_seconds > 0
    assert abs(first.seconds + first.compile_seconds - wall) < 5e-3
    with RenderTimer() as again:
        work()
    assert again.compile_seconds == 0.0  # exact: a cache hit has no back-end time


def test_broken_xml_and_missing_texture_give_clear_errors(tmp_path):
    data_gen.setup_mitsuba()
    bad = tmp_path / "broken.xml"
    bad.write_text("<scene version='3.0.0'><shape type='sphere'></scene>")
    with pytest.raises(data_gen.SceneError, match="broken.xml.*not well-formed"):
        data_gen.load_scene(bad)
    with pytest.raises(data_gen.SceneError, match="missing file 'nope.png'"):
        data_gen.load_scene(_xml(tmp_path, "nope.png"))
    with pytest.raises(data_gen.SceneError, match="does not exist"):
        data_gen.load_scene(tmp_path / "absent.xml")
    wrong = tmp_path / "plugin.xml"
    wrong.write_text("<scene version='3.0.0'><shape type='no_such_shape'/></scene>")
    with pytest.raises(data_gen.SceneError, match="plugin.xml"):
        data_gen.load_scene(wrong)


def test_plan_buffers_leaves_out_what_the_scene_cannot_vary():
    desc = {"emitters": 0, "roughness_values": [1.0], "lens": False}
    fields, left = shot.plan_buffers(desc, data_gen.PathSettings(max_depth=2), None, 4)
    for f in ("albedo2", "albedo2_var", "visibility", "roughness", "dx", "dy"):
        assert f not in fields and f in left, f
    assert "max_depth=2" in left["albedo2"] and "no emitters" in left["visibility"]
    assert fields[:2] == ["color", "color_var"] and "normal" in fields and "lens" in left
    # Asked for explicitly: rendered even though constant here; variances never at 1 spp.
    fields, left = shot.plan_buffers(desc, data_gen.PathSettings(max_depth=2),
                                     frozenset({"color", "color_var", "visibility", "visibility_var"}), 1)
    assert fields == ["color", "visibility"] and "1 spp" in left["color_var"]


@pytest.mark.mitsuba
def test_methods_needs_decide_the_buffers(tmp_path):
    _llvm()
    d = data_gen.default_scene(width=8, height=8)
    rec = data_gen.render_shot(d, tmp_path, spp=(2,), ref_spp=0, buffers=["albedo", "normal"], progress=False)
    assert rec["files"]["spp0002_00.exr"]["fields"] == ["color", "albedo", "normal"]  # exactly what was asked
    assert "visibility" in rec["left_out"]["spp2"]
    rec = data_gen.render_shot(d, tmp_path / "m", spp=(1,), ref_spp=0, methods=["input"], progress=False)
    assert rec["files"]["spp0001_00.exr"]["fields"] == ["color"]
    with pytest.raises(ValueError, match="unknown buffer"):
        data_gen.render_shot(d, tmp_path / "x", spp=(1,), ref_spp=0, buffers=["albdo"], progress=False)


@pytest.mark.mitsuba
def test_interrupted_then_resumed_dataset_equals_uninterrupted(tmp_path):
    _llvm()
    kw = dict(width=8, spp=(1, 2), instances=2, ref_spp=4, progress=False, max_depth=3)
    full = data_gen.generate_dataset("mixed", 2, tmp_path / "full", **kw)
    with pytest.raises(KeyboardInterrupt):
        data_gen.generate_dataset("mixed", 2, tmp_path / "part", _stop_after=2, **kw)
    assert len(list((tmp_path / "part").rglob("*.exr"))) == 2
    assert not list((tmp_path / "part").rglob(".*tmp*")), "a temporary file was left behind"
    resumed = data_gen.generate_dataset("mixed", 2, tmp_path / "part", **kw)
    for scene_name, rec in full["scenes"].items():
        other = resumed["scenes"][scene_name]["files"]
        assert set(other) == set(rec["files"])
        for name, entry in rec["files"].items():
            assert other[name]["data_sha256"] == entry["data_sha256"], f"{scene_name}/{name} differs after resume"
    m = json.loads((tmp_path / "part" / "manifest.json").read_text())
    assert set(m["scenes"]) == {"scene_0000", "scene_0001"}
    again = data_gen.generate_dataset("mixed", 2, tmp_path / "part", **kw)  # nothing left: all skipped
    assert again["scenes"]["scene_0000"]["files"] == resumed["scenes"]["scene_0000"]["files"]


@pytest.mark.mitsuba
def test_every_family_builds():
    _llvm()
    for fam in data_gen.FAMILIES:
        s = data_gen.load_scene(data_gen.build_scene(fam, 3, width=4, height=4))
        assert render.film_size(s) == (4, 4)
    with pytest.raises(data_gen.SceneError, match="family"):
        data_gen.build_scene("castles", 0)


def test_scalar_fallback_renders_the_same_estimator():
    """The scalar_rgb path (used when no LLVM >= 16 exists) on a 3x3 image."""
    import mitsuba as mi

    chosen = data_gen.setup_mitsuba()
    try:
        mi.set_variant("scalar_rgb")
        d = mi.cornell_box()
        d["sensor"]["film"] = {"type": "hdrfilm", "width": 3, "height": 3, "rfilter": {"type": "box"}}
        s = mi.load_dict(d)
        out = render.render_buffers(s, spp=24, seed=0, settings=data_gen.PathSettings(max_depth=3),
                                    record=("albedo", "visibility"))
        assert out["color"].shape == (3, 3, 3) and out["albedo"].shape == (3, 3, 3)
        assert np.all(np.isfinite(out["color"])) and out["color_var"].min() >= 0
        ref = np.asarray(mi.render(s, spp=256, seed=1))
        # 24 spp x 9 pixels: the image mean's relative error is ~10 %; 35 % fails on a broken estimator.
        assert abs(out["color"].mean() / ref.mean() - 1) < 0.35, (out["color"].mean(), ref.mean())
    finally:
        mi.set_variant(chosen)


def test_setup_mitsuba_falls_back_to_scalar_with_one_message():
    """With no usable libLLVM (simulated in a fresh process), scalar_rgb is chosen and one message says why."""
    import subprocess
    import sys

    code = ("import data_gen.mitsuba_setup as m; m.llvm_candidates = lambda: []; "
            "print(m.setup_mitsuba()); print(m.setup_mitsuba())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         cwd=Path(__file__).resolve().parent.parent)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["scalar_rgb", "scalar_rgb"]
    assert out.stderr.count("falling back") == 1 and "apt-get install libllvm19" in out.stderr, out.stderr


@pytest.mark.mitsuba
def test_first_hits_tells_surfaces_emitters_and_sky_apart_and_labels_rebuild_scenes():
    """`render.first_hits` (the colour-level studies' masks): fractions in [0, 1] that sum to at most 1;
    on the built-in scene the pixels whose rays all hit the light are far brighter than the surfaces,
    and pixels inside a region whose rays all hit something have depth > 0. `scenes.scene_from_label` rebuilds a render's scene
    from its record's label (the same hits); an edited library scene and a bad label are refused."""
    _llvm()
    sc = data_gen.load_scene(data_gen.default_scene(width=32, height=32))
    h = render.first_hits(sc, spp=8)
    surf, em = h["surface"], h["emitter"]
    assert surf.shape == em.shape == (32, 32) and surf.min() >= 0 and (surf + em).max() <= 1 + 1e-12
    assert (em >= 1).sum() >= 4 and (surf >= 1).sum() > 500 and ((surf + em) == 0).sum() >= 1
    b = render.render_buffers(sc, spp=8, seed=1, settings=integrator.PathSettings(), record={"depth"})
    lum = b["color"].mean(-1)
    assert np.median(lum[em >= 1]) > 5 * np.median(lum[surf >= 1])
    from scipy.ndimage import minimum_filter
    inside = minimum_filter(surf + em, size=3) >= 1  # every ray of the pixel and its neighbours hit a shape
    assert inside.sum() > 400 and (b["depth"][..., 0][inside] > 0).all()
    a = render.first_hits(scenes.scene_from_label("mixed:5", width=16, height=12), spp=4)
    ref = render.first_hits(data_gen.load_scene(data_gen.build_scene("mixed", 5, width=16, height=12)), spp=4)
    np.testing.assert_array_equal(a["surface"], ref["surface"])
    with pytest.raises(data_gen.SceneError, match="changed since"):
        scenes.scene_from_label("library:chess@000000000000", width=8, height=6)
    with pytest.raises(data_gen.SceneError, match="family:seed"):
        scenes.scene_from_label("castles:3", width=8, height=6)


def test_first_hits_counts_the_back_of_a_one_sided_light_as_a_surface():
    """A one-sided area light (Mitsuba's ``area`` emits on its normal's side) seen from behind is black
    in the render: `render.first_hits` counts it a surface, and an emitter from the front (the levels
    study divided outputs by a black reference on such pixels)."""
    _llvm()
    import mitsuba as mi

    def looking_from(z):
        return mi.load_dict({"type": "scene", "sensor": {
            "type": "perspective", "fov": 60,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, z], target=[0, 0, 0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"}}},
            "light": {"type": "rectangle", "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 5.0}}}})

    front, back = render.first_hits(looking_from(3.0), spp=4), render.first_hits(looking_from(-3.0), spp=4)
    assert front["emitter"].sum() > 40 and front["surface"].sum() == 0
    assert back["emitter"].sum() == 0
    np.testing.assert_array_equal(back["surface"], front["emitter"])
