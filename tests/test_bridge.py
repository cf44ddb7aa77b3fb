"""Mitsuba renders handed to jaxdenoise in memory, and denoisers differentiated from Dr.Jit (issue 39).

- `data_gen.render_frame` gives the `Buffers` `render_shot`'s EXR holds, bit for bit (the EXR stores
  float32); `buffers_from_tensor` reads an ``aov`` integrator's tensor as its film's EXR reads;
- ``dr.backward`` through `data_gen.differentiable` equals finite differences of the same samples: the
  loss's cotangent on the image (`jax.vjp` of the pure JAX function, taken apart from Dr.Jit) dotted
  with the central difference of renders at PRB's gradient seed, for a diffuse albedo and a light's
  radiance, through `gaussian` and `demc`; the Dr.Jit-side image gradient equals `jax.vjp` directly;
- foreign code (OIDN) and malformed calls are refused by name.
"""
from __future__ import annotations

import numpy as np
import pytest

import data_gen
import jaxdenoise as jd
from jaxdenoise.errors import JaxdenoiseError
from jaxdenoise.io import read_buffers

SIZE = 32  # demc needs multiples of 32
SEED, SEED_GRAD = 7, 8  # mi.render's primal and gradient seeds (Mitsuba refuses equal ones)


def _mitsuba():
    import drjit as dr
    import mitsuba as mi

    v = data_gen.setup_mitsuba()
    assert v == "llvm_ad_rgb", f"these tests need Mitsuba's llvm_ad_rgb variant; setup_mitsuba() chose {v!r}"
    return mi, dr


def _box(width: int = SIZE, height: int = SIZE) -> dict:
    mi, _ = _mitsuba()
    d = mi.cornell_box()
    d["sensor"]["film"].update(width=width, height=height, rfilter={"type": "box"})
    return d


@pytest.fixture(scope="module")
def box():
    mi, _ = _mitsuba()
    scene = mi.load_dict(_box())
    return scene, mi.traverse(scene)


def test_render_frame_equals_the_exr_round_trip(tmp_path):
    scene = _box(12, 9)  # odd sizes
    mem = data_gen.render_frame(scene, spp=4, methods=["lbf", "demc"], seed=3, max_depth=3)
    rec = data_gen.render_shot(scene, tmp_path, spp=[4], ref_spp=0, methods=["lbf", "demc"], seed=3, max_depth=3,
                               progress=False)
    disk, _ = read_buffers(tmp_path / "spp0004_00.exr")
    assert mem.present() == disk.present() == set(rec["files"]["spp0004_00.exr"]["fields"]) | {"spp", "world_to_camera", "world_to_ndc"}
    for field in sorted(mem.present()):
        np.testing.assert_array_equal(np.asarray(getattr(mem, field)), np.asarray(getattr(disk, field)), err_msg=field)
    # jaxdenoise.denoise takes it directly, with the result of the file
    np.testing.assert_array_equal(jd.denoise(mem, "gaussian"), jd.denoise(disk, "gaussian"))


def test_buffers_from_an_aov_tensor_equal_its_film_exr(tmp_path):
    mi, _ = _mitsuba()
    d = _box(10, 8)
    d["integrator"] = {"type": "aov", "aovs": "nn:sh_normal,dd:depth,albedo:albedo,pp:position",
                       "inner": {"type": "path", "max_depth": 3}}
    d["sensor"]["film"]["component_format"] = "float32"
    scene = mi.load_dict(d)
    tensor = mi.render(scene, spp=4, seed=1)
    assert data_gen.bridge.tensor_channel_names(scene.integrator(), tensor.shape[-1])[:4] == ["R", "G", "B", "nn.X"]
    mem = data_gen.buffers_from_tensor(tensor, integrator=scene.integrator(), spp=4, camera_scene=scene)
    scene.sensors()[0].film().write(str(tmp_path / "film.exr"))
    disk, _ = read_buffers(tmp_path / "film.exr", spp=4)
    assert {"color", "normal", "depth", "albedo", "position", "spp", "world_to_camera"} <= mem.present()
    for field in ("color", "normal", "depth", "albedo", "position", "spp"):
        # the film's bitmap and mi.render's tensor are developed apart: up to 1 ulp (float32) between them
        np.testing.assert_allclose(np.asarray(getattr(mem, field)), np.asarray(getattr(disk, field)), rtol=3e-7,
                                   atol=1e-12, err_msg=field)
    # an aov integrator without an inner one: the colour comes separately
    aovs = np.asarray(tensor)[..., 3:]
    names = data_gen.bridge.tensor_channel_names(scene.integrator(), tensor.shape[-1])[3:]
    only = data_gen.buffers_from_tensor(aovs, names, color=np.asarray(tensor)[..., :3], spp=4)
    np.testing.assert_array_equal(only.normal, mem.normal)
    with pytest.raises(JaxdenoiseError, match=r"3 name\(s\).*13 channel"):
        data_gen.buffers_from_tensor(tensor, ["R", "G", "B"], spp=4)
    with pytest.raises(JaxdenoiseError, match="names= .*or integrator="):
        data_gen.buffers_from_tensor(tensor, spp=4)


def _grad_and_fd(scene, params, method: str, key: str):
    """(d loss / d theta by dr.backward through the wrapped denoiser, the same by central differences
    of the renders at the gradient seed, dotted with the cotangent jax.vjp gives on the image)."""
    import jax
    import jax.numpy as jnp

    mi, dr = _mitsuba()
    prb = mi.load_dict({"type": "prb", "max_depth": 3})  # below PRB's rr_depth (5): no roulette
    base = mi.Color3f(params[key])
    den = data_gen.differentiable(method)
    aux = den.aux(scene, spp=4, seed=3, max_depth=3)
    target = np.full((SIZE, SIZE, 3), 0.3, np.float32)

    def render(theta: float, seed: int, grad: bool = False):
        th = mi.Float(theta)
        if grad:
            dr.enable_grad(th)
        params[key] = base * th
        params.update()
        return th, mi.render(scene, params, spp=4, seed=seed, seed_grad=seed + 1, integrator=prb)

    th, img = render(1.0, SEED, grad=True)
    loss = dr.mean(dr.square(den(img, aux) - mi.TensorXf(target)), axis=None)
    dr.backward(loss)
    ad = float(np.asarray(dr.grad(th)).reshape(-1)[0])
    f = den.jax_fn(aux)
    arrays = {k: jnp.asarray(np.asarray(v)) for k, v in aux.items() if k != "spp"}
    out, vjp = jax.vjp(lambda c: f(c, arrays), jnp.asarray(np.asarray(dr.detach(img))))
    cot = vjp(2.0 * (out - target) / out.size)[0]  # d mean((out - target)^2) / d image
    eps = 1e-2
    with dr.suspend_grad():
        plus, minus = np.asarray(render(1 + eps, SEED_GRAD)[1]), np.asarray(render(1 - eps, SEED_GRAD)[1])
    params[key] = base
    params.update()
    assert np.all(np.isfinite(np.asarray(cot)))
    return ad, float(np.sum(np.asarray(cot, np.float64) * (plus - minus)) / (2 * eps))


@pytest.mark.parametrize("method", ["gaussian", "demc"])
@pytest.mark.parametrize("key", ["red.reflectance.value", "light.emitter.radiance.value"])
def test_gradients_through_the_denoiser_match_finite_differences(box, method, key):
    scene, params = box
    ad, fd = _grad_and_fd(scene, params, method, key)
    assert ad != 0.0
    # same samples on both sides: the render is a polynomial of degree <= 3 in theta, so the central
    # difference is exact to O(eps^2) ~ 1e-4 relative; float32 sums add ~1e-5
    assert abs(ad - fd) <= 1e-3 * abs(fd), (method, key, ad, fd)


@pytest.mark.parametrize("method", ["gaussian", "demc"])
def test_the_image_gradient_is_jax_vjp(box, method):
    import jax
    import jax.numpy as jnp

    mi, dr = _mitsuba()
    scene, _ = box
    den = data_gen.differentiable(method)
    aux = den.aux(scene, spp=4, seed=5, max_depth=3)
    image = np.asarray(mi.render(scene, spp=4, seed=2))
    w = np.random.default_rng(0).standard_normal(image.shape).astype(np.float32)
    color = mi.TensorXf(image)
    dr.enable_grad(color)
    out = den(color, aux)
    dr.backward(dr.sum(out * mi.TensorXf(w), axis=None))
    arrays = {k: jnp.asarray(np.asarray(v)) for k, v in aux.items() if k != "spp"}
    value, vjp = jax.vjp(lambda c: den.jax_fn(aux)(c, arrays), jnp.asarray(image))
    np.testing.assert_allclose(np.asarray(dr.grad(color)), np.asarray(vjp(jnp.asarray(w))[0]), rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(np.asarray(dr.detach(out)), np.asarray(value))


def test_foreign_methods_and_bad_calls_are_refused(box):
    mi, _ = _mitsuba()
    scene, _ = box
    with pytest.raises(JaxdenoiseError, match="'oidn' runs foreign code.*gaussian"):
        data_gen.differentiable("oidn")
    lbf = data_gen.differentiable("lbf")
    with pytest.raises(JaxdenoiseError, match=r"reads variances .*spp >= 2; got spp=1"):
        lbf.aux(scene, spp=1)
    den = data_gen.differentiable("demc")
    image = mi.render(scene, spp=1, seed=1)
    with pytest.raises(jd.BuffersError, match=r"needs buffer\(s\) \[.albedo., .albedo2., .normal., .position.\]"):
        den(image, {"spp": 1})
    with pytest.raises(JaxdenoiseError, match="expected a Dr.Jit tensor"):
        den(np.asarray(image), {})
    with pytest.raises(JaxdenoiseError, match=r"unknown buffer name\(s\) \['albedo_map'\]"):
        den(image, {"albedo_map": image})
