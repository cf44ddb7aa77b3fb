"""Gradient-domain path tracing with the reconnection shift (`data_gen.gpt`, issue 16).

Unbiasedness is checked as for the replay shift (tests/test_gradient.py): the mean of dx, dy over
256 samples against the finite differences of an 8192-spp plain render with an independent seed,
as z-scores against the variances both renderers estimate (|z| < 5 over 97 block and image sums per
buffer). The scenes are 16x16 (a sphere on a checkered floor under a rectangular light and a sky),
with the sphere's material varied so that every branch of the shift runs: reconnection (diffuse,
rough glossy, rough glass), half-vector copying through a near-specular lobe, the delta lobes of a
mirror, glass and smooth plastic, and a thin-lens camera.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from data_gen.gradient import render_gradients
from data_gen.integrator import PathSettings
from data_gen.mitsuba_setup import setup_mitsuba
from data_gen.render import render_buffers

pytestmark = pytest.mark.mitsuba

RES = 16
SPP = 256
REF_SPP = 8192


def _mi():
    setup_mitsuba()
    import mitsuba as mi

    return mi


def sphere_scene(ball_bsdf: dict | None = None, *, floor: dict | None = None, dof: bool = False, res: int = RES):
    mi = _mi()
    T = mi.ScalarTransform4f
    rgb = lambda v: {"type": "rgb", "value": v}  # noqa: E731
    sensor = {"type": "perspective", "fov": 45,
              "to_world": T().look_at(origin=[0, 2.2, 4.2], target=[0, 0.4, 0], up=[0, 1, 0]),
              "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}}
    if dof:
        sensor.update(type="thinlens", aperture_radius=0.15, focus_distance=3.0)
    return mi.load_dict({
        "type": "scene", "sensor": sensor,
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(5),
                  "bsdf": floor or {"type": "diffuse", "reflectance": {"type": "checkerboard", "to_uv": T().scale(8)}}},
        "ball": {"type": "sphere", "center": [0, 0.6, 0], "radius": 0.6,
                 "bsdf": ball_bsdf or {"type": "diffuse", "reflectance": rgb([0.7, 0.3, 0.2])}},
        "back": {"type": "sphere", "center": [-1.2, 0.4, -1.0], "radius": 0.4,
                 "bsdf": {"type": "diffuse", "reflectance": rgb([0.2, 0.5, 0.8])}},
        "light": {"type": "rectangle", "to_world": T().translate([1.0, 3.0, 1.0]).rotate([1, 0, 0], 90).scale(0.8),
                  "emitter": {"type": "area", "radiance": rgb([8, 8, 8])}},
        "sky": {"type": "constant", "radiance": rgb([0.3, 0.35, 0.4])},
    })


CASES = {
    "rough-glossy": dict(ball_bsdf={"type": "roughconductor", "material": "Au", "distribution": "ggx", "alpha": 0.2}),
    "near-specular": dict(ball_bsdf={"type": "roughconductor", "material": "Cu", "distribution": "ggx",
                                     "alpha": 0.0005}),
    "mirror": dict(ball_bsdf={"type": "conductor", "material": "Ag"}),
    "glass": dict(ball_bsdf={"type": "dielectric", "int_ior": 1.5}),
    "rough-glass": dict(ball_bsdf={"type": "roughdielectric", "int_ior": 1.5, "distribution": "ggx", "alpha": 0.2}),
    "plastic": dict(ball_bsdf={"type": "plastic", "diffuse_reflectance": {"type": "rgb", "value": [0.7, 0.2, 0.2]}},
                    floor={"type": "roughplastic", "distribution": "ggx", "alpha": 0.1,
                           "diffuse_reflectance": {"type": "rgb", "value": [0.4, 0.4, 0.4]}}),
    "depth-of-field": dict(dof=True),
}


def _z_scores(d, v):
    """Per-channel z of the summed difference in each 4x4 block and over the whole image."""
    h, w = d.shape[:2]
    z = []
    for y in range(0, h - h % 4, 4):
        for x in range(0, w - w % 4, 4):
            s, var = d[y:y + 4, x:x + 4].sum((0, 1)), v[y:y + 4, x:x + 4].sum((0, 1))
            z.append(np.where(var > 0, s / np.sqrt(np.maximum(var, 1e-30)), 0.0))
    z.append(d.sum((0, 1)) / np.sqrt(np.maximum(v.sum((0, 1)), 1e-30)))
    return np.abs(np.stack(z))


def _max_z(g, ref) -> dict[str, float]:
    r, rv = ref["color"], ref["color_var"]
    cases = {
        "dx": (g["dx"][:, :-1] - (r[:, 1:] - r[:, :-1]), g["dx_var"][:, :-1] + rv[:, 1:] + rv[:, :-1]),
        "dy": (g["dy"][:-1] - (r[1:] - r[:-1]), g["dy_var"][:-1] + rv[1:] + rv[:-1]),
        "primal": (g["primal"] - r, g["primal_var"] + rv),
    }
    return {k: float(_z_scores(e, v).max()) for k, (e, v) in cases.items()}


def _reference(scene):
    return render_buffers(scene, spp=REF_SPP, seed=987654, settings=PathSettings())


@pytest.fixture(scope="module")
def diffuse():
    scene = sphere_scene()
    return scene, _reference(scene)


def test_base_paths_are_the_plain_render(diffuse):
    """Issue 16 check: the reconnect tracer's base image is bit-identical to `render_buffers` with the
    same seed (same lanes, camera samples and path decisions), also when split into passes."""
    scene, _ = diffuse
    for per_pass in (RES * RES * 3, 1 << 20):
        g = render_gradients(scene, spp=8, seed=11, samples_per_pass=per_pass, shift="reconnect")
        r = render_buffers(scene, spp=8, seed=11, settings=PathSettings(), samples_per_pass=per_pass)
        assert np.array_equal(g["primal"], r["color"])  # tolerance: bit-identical
        assert np.array_equal(g["primal_var"], r["color_var"])


def test_unbiased_on_a_diffuse_scene(diffuse):
    """dx, dy and the G-PT primal match the reference (|z| < 5; measured max 3.2), most offset
    paths reconnect (measured 0.64 of all offsets; the rest see the sky directly or fail at the
    sphere's silhouette: 0.07), and the variance of dx is below the replay shift's on the same
    scene (measured 0.62x: a diffuse scene under direct light is the replay shift's best case). The
    G-PT primal's variance is 0.34x the base image's (tolerance 0.7x)."""
    scene, ref = diffuse
    g = render_gradients(scene, spp=SPP, seed=0, shift="reconnect", primal="gpt")
    z = _max_z(g, ref)
    assert max(z.values()) < 5.0, z
    st = g["shift_stats"]
    assert st["offset_paths"] == 4 * RES * RES * SPP
    assert st["reconnected"] > 0.5 and st["failed"] < 0.2, st
    assert g["n_invalid"] == 0
    replay = render_gradients(scene, spp=SPP, seed=0, shift="replay")
    assert g["dx_var"].mean() < replay["dx_var"].mean()
    # The G-PT primal (MIS over both ends of each pair) has lower variance than the base image.
    base = render_gradients(scene, spp=SPP, seed=0, shift="reconnect")
    assert g["primal_var"].mean() < 0.7 * base["primal_var"].mean()


@pytest.mark.parametrize("case", list(CASES))
def test_unbiased_on_glossy_specular_glass_and_depth_of_field(case):
    """The same check on every BSDF class the shift supports and on a thin lens (|z| < 5; measured
    max 3.4). Near-specular, mirror, glass and smooth plastic go through half-vector copying."""
    scene = sphere_scene(**CASES[case])
    ref = _reference(scene)
    g = render_gradients(scene, spp=SPP, seed=0, shift="reconnect", primal="gpt")
    z = _max_z(g, ref)
    assert max(z.values()) < 5.0, (case, z)
    assert g["n_invalid"] == 0
    st = g["shift_stats"]
    if case in ("near-specular", "mirror", "glass"):
        assert st["half_vector"] > 0.02, st
    assert 0.0 <= st["failed"] < 0.25, st


@pytest.mark.parametrize("wrong", ["jacobian", "mis"])
def test_a_wrong_jacobian_or_mis_weight_is_caught(monkeypatch, wrong):
    """The control: the same statistic fails when the reconnection Jacobian is replaced by 1 or when
    each end of a pixel pair weights itself as if the other did not exist (MIS denominators
    without the offset terms). Measured max |z|: 15 (Jacobian), 10 (MIS)."""
    import drjit as dr

    import data_gen.gpt as gpt

    scene = sphere_scene(**CASES["rough-glossy"])
    ref = _reference(scene)
    if wrong == "jacobian":
        monkeypatch.setattr(gpt, "_reconnection_jacobian", lambda cos_y, d2y, cos_x, d2x: dr.abs(cos_y) * 0 + 1.0)
    else:
        monkeypatch.setattr(gpt, "_pair_weight", lambda base_terms, offset_terms: dr.rcp(base_terms + 0 * offset_terms))
    g = render_gradients(scene, spp=SPP, seed=0, shift="reconnect")
    z = _max_z(g, ref)
    assert max(z["dx"], z["dy"]) > 5.0, z


def test_translation_invariant_plane_gives_exact_zero_gradients():
    """An orthographic camera over an infinite plane under a sun and a sky: every offset path
    reconnects and carries exactly the base's radiance, so dx, dy vanish (tolerance 1e-5 absolute,
    float32 rounding) while the image itself is noisy."""
    mi = _mi()
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "orthographic",
                   "to_world": T().look_at(origin=[0, 5, 0], target=[0, 0, 0], up=[0, 0, 1]).scale([2, 2, 1]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {"type": "box"}}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(1000),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.6, 0.7]}}},
        "sun": {"type": "directional", "direction": [0.3, -1, 0.2], "irradiance": {"type": "rgb", "value": [2, 2, 2]}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.4, 0.4, 0.4]}},
    })
    g = render_gradients(scene, spp=16, seed=5, shift="reconnect")
    assert g["primal_var"].mean() > 1e-4
    for k in ("dx", "dy"):
        assert np.abs(g[k]).max() < 1e-5, k
    assert g["shift_stats"]["reconnected"] == 1.0 and g["shift_stats"]["failed"] == 0.0


@pytest.mark.parametrize("family", ["rooms", "objects", "dof", "thin", "fireflies", "envmap"])
def test_procedural_families_give_finite_gradients(family):
    """Every procedural family (the stability scenes of data_gen): finite dx, dy and primal, shift
    statistics in [0, 1], no non-finite lane."""
    from data_gen.scenes import build_scene, load_scene

    _mi()
    scene = load_scene(build_scene(family, 7, width=32, height=32))
    g = render_gradients(scene, spp=8, seed=1, shift="reconnect", primal="gpt")
    for k in ("dx", "dy", "primal", "dx_var", "dy_var", "primal_var"):
        assert np.all(np.isfinite(g[k])), (family, k)
    st = g["shift_stats"]
    assert all(0.0 <= st[k] <= 1.0 for k in ("reconnected", "half_vector", "failed")), st
    assert g["n_invalid"] == 0


def test_bad_arguments_name_what_was_expected(diffuse):
    scene, _ = diffuse
    with pytest.raises(ValueError, match="shift"):
        render_gradients(scene, spp=2, shift="mirror")
    with pytest.raises(ValueError, match="primal"):
        render_gradients(scene, spp=2, primal="mean")
    with pytest.raises(ValueError, match="shift='reconnect'"):
        render_gradients(scene, spp=2, shift="replay", primal="gpt")
    with pytest.raises(ValueError, match="roughness_threshold"):
        render_gradients(scene, spp=2, shift="reconnect", roughness_threshold=-1.0)


def test_shot_records_the_shift(tmp_path):
    """`render_shot` writes the shift into the frame's key, EXR header and manifest entry (with the
    shift statistics); a changed shift re-renders the gradient frame, the reference is kept."""
    from data_gen.shot import render_shot
    from jaxdenoise.io import read_buffers

    scene = sphere_scene(res=8)
    rec = render_shot(scene, tmp_path, spp=[2], ref_spp=4, methods=["poisson-l2"], shift="reconnect",
                      progress=False)
    entry = rec["files"]["spp0002_00.exr"]
    assert entry["key"]["shift"] == "reconnect" and entry["key"]["primal"] == "base"
    assert 0.0 < entry["shift_stats"]["reconnected"] <= 1.0
    frame, attrs = read_buffers(tmp_path / "spp0002_00.exr")
    assert attrs["gradient_shift"] == "reconnect"
    assert frame.dx is not None and frame.dy is not None
    ref_sha = rec["files"]["reference.exr"]["sha256"]
    rec2 = render_shot(scene, tmp_path, spp=[2], ref_spp=4, methods=["poisson-l2"], shift="replay", progress=False)
    assert rec2["files"]["spp0002_00.exr"]["key"]["shift"] == "replay"
    assert rec2["files"]["reference.exr"]["sha256"] == ref_sha
    assert json.loads((tmp_path / "shot.json").read_text())["files"]["spp0002_00.exr"]["key"]["shift"] == "replay"


def test_a_gradient_shot_is_one_pass_and_times_the_buffer_pass_beside_it(tmp_path, monkeypatch):
    """A gradient frame of a shot is rendered in one pass (colour, features, dx, dy); its buffers
    equal a plain shot's of the same seed bit for bit, the buffer-only render is timed beside it
    (``buffer_seconds``, what bench charges a method that reads no gradient), and a buffer pass that
    disagreed with the one pass would stop the shot with an error naming the buffer."""
    from data_gen import shot
    from jaxdenoise.data import discover
    from jaxdenoise.io import read_buffers

    scene = sphere_scene(res=8)
    rec = shot.render_shot(scene, tmp_path / "g", spp=[2], ref_spp=4, methods=["poisson-l2", "lbf"],
                           progress=False)
    entry = rec["files"]["spp0002_00.exr"]
    assert entry["seconds"] > 0 and entry["buffer_seconds"] > 0 and "one pass" in entry["gradient_note"]
    assert "gradient_seconds" not in entry
    assert rec["render_seconds"] == pytest.approx(sum(v["seconds"] + v.get("buffer_seconds", 0.0)
                                                      for v in rec["files"].values()))
    (render,) = discover(tmp_path / "g")[0].renders
    assert render.render_seconds == pytest.approx(entry["seconds"])
    assert render.buffer_seconds == pytest.approx(entry["buffer_seconds"])
    shot.render_shot(scene, tmp_path / "p", spp=[2], ref_spp=0, methods=["lbf"], progress=False)
    g, _ = read_buffers(tmp_path / "g" / "spp0002_00.exr")
    p, _ = read_buffers(tmp_path / "p" / "spp0002_00.exr")
    assert g.dx is not None and p.dx is None
    for f in ("color", "color_var", "albedo", "normal", "depth", "albedo_var"):
        np.testing.assert_array_equal(getattr(g, f), getattr(p, f), err_msg=f)

    real = shot.render_buffers

    def off_by_one_ulp(*a, **kw):
        out = real(*a, **kw)
        out["albedo"] = np.nextafter(out["albedo"], np.float32(np.inf))
        return out

    monkeypatch.setattr(shot, "render_buffers", off_by_one_ulp)
    with pytest.raises(RuntimeError, match="albedo: the one-pass gradient render differs"):
        shot.render_shot(scene, tmp_path / "bad", spp=[2], ref_spp=0, methods=["poisson-l2", "lbf"], progress=False)


@pytest.mark.parametrize("shift", ["reconnect", "replay"])
def test_the_gradient_pass_records_the_buffer_pass_features(shift):
    """A gradient frame needs no plain buffer pass: the base paths of the gradient render record the
    colour and every feature exactly as `render_buffers` does for the same seed (bit-identical, with
    their variances), on glass, plastic and rough metal, also where the path length cap makes the
    last allowed vertex the feature vertex (max_depth 1 and 2)."""
    from data_gen.integrator import FEATURES
    from data_gen.scenes import build_scene, load_scene

    scene = load_scene(build_scene("objects", 2, width=RES, height=RES))
    for depth in (1, 2, 8):
        plain = render_buffers(scene, spp=2, seed=3, settings=PathSettings(max_depth=depth), record=FEATURES)
        g = render_gradients(scene, spp=2, seed=3, max_depth=depth, shift=shift, record=FEATURES)
        np.testing.assert_array_equal(g["primal"], plain["color"])
        np.testing.assert_array_equal(g["primal_var"], plain["color_var"])
        for f in FEATURES:
            np.testing.assert_array_equal(g[f], plain[f], err_msg=f"{f}, max_depth {depth}")
            np.testing.assert_array_equal(g[f + "_var"], plain[f + "_var"], err_msg=f"{f}_var, max_depth {depth}")
        assert float(np.max(plain["albedo2"])) > 0 and float(np.max(plain["visibility"])) > 0 or depth == 1
    with pytest.raises(ValueError, match="record: unknown feature"):
        render_gradients(scene, spp=1, seed=0, record=("albedo", "colour"))


def test_the_state_branches_give_the_one_trace_of_every_state_bit_for_bit(monkeypatch):
    """The tracer runs the reconnection / half-vector code only in the SIMD packets whose offsets have
    not yet connected (`trace_gpt(branch_states=True)`, the default: symbolic conditionals per offset
    state). Every output (gradients, pair estimates, G-PT primal, emission, shift statistics) equals
    the single trace of every state bit for bit, on a scene that reconnects (rough plastic, diffuse),
    copies half-vectors and takes delta lobes (a glass sphere and a near-specular one, thin lens)."""
    import functools

    import data_gen.gpt as gpt
    import data_gen.gradient as gradient
    from data_gen.scenes import build_scene, load_scene

    scenes = [load_scene(build_scene("objects", 2, width=RES, height=RES)),
              sphere_scene(**CASES["near-specular"], dof=True), sphere_scene(**CASES["glass"])]
    for scene in scenes:
        outs = []
        for branch in (True, False):
            monkeypatch.setattr(gradient, "trace_gpt", functools.partial(gpt.trace_gpt, branch_states=branch))
            outs.append(render_gradients(scene, spp=4, seed=5, shift="reconnect", primal="gpt"))
        a, b = outs
        assert a["shift_stats"] == b["shift_stats"] and a["n_invalid"] == b["n_invalid"]
        for k, v in a.items():
            if isinstance(v, np.ndarray):
                np.testing.assert_array_equal(v, b[k], err_msg=k)  # tolerance: bit-identical
    assert a["shift_stats"]["half_vector"] > 0.0 and a["shift_stats"]["reconnected"] > 0.0


def test_the_base_primal_leaves_the_pair_estimates_out_bit_for_bit(monkeypatch):
    """With ``primal="base"`` the tracer carries no pair estimates (`trace_gpt(pair_estimates=False)`:
    they make the G-PT primal only); every output equals the tracer that carries them, bit for bit,
    on a scene that reconnects, copies half-vectors and sees a light directly."""
    import functools

    import data_gen.gpt as gpt
    import data_gen.gradient as gradient
    from data_gen.scenes import build_scene, load_scene

    seen = []

    def spy(*args, **kw):
        out = gpt.trace_gpt(*args, **kw)
        seen.append((kw["pair_estimates"], "main" in out, "shifted" in out))
        return out

    monkeypatch.setattr(gradient, "trace_gpt", spy)
    for scene in (load_scene(build_scene("objects", 2, width=RES, height=RES)), sphere_scene(**CASES["near-specular"])):
        lean = render_gradients(scene, spp=4, seed=5, shift="reconnect")
        monkeypatch.setattr(gradient, "trace_gpt", functools.partial(gpt.trace_gpt, pair_estimates=True))
        full = render_gradients(scene, spp=4, seed=5, shift="reconnect")
        monkeypatch.setattr(gradient, "trace_gpt", spy)
        assert lean["shift_stats"] == full["shift_stats"] and lean["n_invalid"] == full["n_invalid"]
        assert lean.keys() == full.keys()
        for k, v in lean.items():
            if isinstance(v, np.ndarray):
                np.testing.assert_array_equal(v, full[k], err_msg=k)  # tolerance: bit-identical
    assert seen and all(s == (False, False, False) for s in seen), seen


@pytest.mark.parametrize("env", ["envmap", "constant"])
def test_an_environment_gives_every_vertex_the_same_density_and_radiance(env):
    """The offsets' light samples take an environment's direction density and radiance from the base's
    sample (`data_gen.gpt`, next-event estimation: same direction, no second lookup). The premise, against
    Mitsuba's own lookups: from another point they equal the lookups from the sampling point bit for bit,
    and those equal the sample's values within Mitsuba's round trip (the envmap's density: direction ->
    uv, up to 2e-4 relative near its poles, median 1 ulp; radiance: 1e-5)."""
    from data_gen.scenes import procedural_envmap

    mi = _mi()
    import drjit as dr

    rng = np.random.default_rng(3)
    emitter = ({"type": "envmap", "bitmap": mi.Bitmap(procedural_envmap(rng)), "scale": 1.3} if env == "envmap"
               else {"type": "constant", "radiance": {"type": "rgb", "value": [0.3, 0.5, 0.7]}})
    scene = mi.load_dict({"type": "scene", "env": emitter})
    n = 4096
    u = rng.random((6, n)).astype(np.float32)
    it = dr.zeros(mi.SurfaceInteraction3f, n)
    it.p = mi.Point3f(*(mi.Float(v) for v in u[:3] * 4 - 2))
    ds, weight = scene.sample_emitter_direction(it, mi.Point2f(mi.Float(u[3]), mi.Float(u[4])), False, True)
    other = dr.zeros(mi.SurfaceInteraction3f, n)
    other.p = it.p + mi.Vector3f(0.7, -0.3, float(u[5, 0]))
    ds_o = dr.zeros(mi.DirectionSample3f, n)
    # as the tracer's copy (`data_gen.gpt`): the base sample's fields, the point moved with the vertex
    ds_o.p, ds_o.n, ds_o.uv, ds_o.d, ds_o.dist = other.p + (ds.p - it.p), ds.n, ds.uv, ds.d, ds.dist
    ds_o.time, ds_o.delta, ds_o.emitter, ds_o.pdf = ds.time, ds.delta, ds.emitter, ds.pdf

    def lookups(ref, d):
        return (np.asarray(scene.pdf_emitter_direction(ref, d, True)),
                np.stack([np.asarray(c) for c in scene.eval_emitter_direction(ref, d, True)]))

    (pdf_o, le_o), (pdf_x, le_x) = lookups(other, ds_o), lookups(it, ds)
    np.testing.assert_array_equal(pdf_o, pdf_x)  # tolerance: bit-identical (the direction alone counts)
    np.testing.assert_array_equal(le_o, le_x)
    pdf, le = np.asarray(ds.pdf), np.stack([np.asarray(c) for c in weight * ds.pdf])
    assert np.all(pdf > 0) and np.all(le > 0)
    np.testing.assert_allclose(pdf_x, pdf, rtol=2e-4)
    assert np.median(np.abs(pdf_x / pdf - 1)) <= 1.2e-7
    np.testing.assert_allclose(le_x, le, rtol=1e-5)
