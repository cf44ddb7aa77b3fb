import jax
import numpy as np
import pytest

import jaxdenoise as jd
from jaxdenoise.inference import prepare
from jaxdenoise.buffers import BuffersError
from jaxdenoise.methods import MethodError, get

from conftest import synthetic_frame


def _gaussian_reference(img: np.ndarray, sigma: float) -> np.ndarray:
    """Brute force in float64: each pixel's in-image neighbours within ceil(3 sigma), weighted by
    exp(-d^2 / (2 sigma^2)) and renormalised (the `gaussian` method's definition)."""
    h, w, _ = img.shape
    r = int(np.ceil(3 * sigma))
    out = np.zeros(img.shape)
    for y in range(h):
        for x in range(w):
            ys, xs = np.mgrid[max(0, y - r):min(h, y + r + 1), max(0, x - r):min(w, x + r + 1)]
            wt = np.exp(-((ys - y) ** 2 + (xs - x) ** 2) / (2 * sigma ** 2))
            out[y, x] = (wt[..., None] * img[ys, xs]).sum((0, 1)) / wt.sum()
    return out


def test_denoise_and_load_agree_with_a_brute_force_blur():
    b = synthetic_frame(h=16, w=12)
    want = _gaussian_reference(np.asarray(b.color, np.float64), get("gaussian").config.sigma)
    np.testing.assert_allclose(jd.denoise(b, method="gaussian"), want, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(jd.load("gaussian")(b)), want, rtol=1e-5, atol=1e-6)


def test_jit_and_nonjit_agree():
    b = synthetic_frame(h=16, w=12)
    m = get("gaussian")
    eager = np.asarray(m.apply({}, b))
    jitted = np.asarray(jax.jit(lambda p, x: m.apply(p, x))({}, b))
    np.testing.assert_allclose(jitted, eager, rtol=1e-6, atol=1e-7)


def test_input_is_identity_and_gaussian_smooths():
    b = synthetic_frame(h=16, w=16)
    np.testing.assert_array_equal(jd.denoise(b, method="input"), b.color)
    out = jd.denoise(b, method="gaussian")
    assert out.shape == b.color.shape and out.std() < 0.8 * b.color.std()  # blur lowers variance


def test_prepare_feeds_only_what_method_reads():
    b = synthetic_frame()
    # the frame's metadata (spp, the camera) always travels with it (docs/architecture.md "Methods")
    meta = {"spp", "world_to_camera"}
    assert prepare(get("gaussian"), b).present() == {"color"} | meta
    assert prepare(get("oidn"), b).present() == {"color", "albedo", "normal"} | meta
    assert prepare(get("oidn"), b.only(())).present() == {"color"} | meta  # OIDN runs on colour alone


def test_unknown_method_and_nonfinite_input():
    b = synthetic_frame()
    with pytest.raises(MethodError, match="unknown method 'nope'; registered: input, gaussian"):
        jd.denoise(b, method="nope")
    c = b.color.copy()
    c[0, 0, 0] = np.nan
    with pytest.raises(BuffersError, match=r"buffer 'color' has 1 NaN/Inf value\(s\)"):
        jd.denoise(b.replace(color=c), method="gaussian")


def test_oidn_runs_with_and_without_aux():
    b = synthetic_frame(h=16, w=16)
    full = jd.denoise(b, method="oidn")
    with pytest.warns(jd.JaxdenoiseWarning, match=r"oidn ran without optional buffer\(s\) \['albedo', 'normal'\]"):
        plain = jd.denoise(b.only(()), method="oidn")  # said, not silent
    assert full.shape == plain.shape == b.color.shape
    assert np.isfinite(full).all() and not np.allclose(full, plain, atol=1e-6)  # aux changes the result


def test_oidn_missing_package_is_clear(monkeypatch):
    import builtins

    real = builtins.__import__

    def fake(name, *a, **k):
        if name == "pyoidn":
            raise ImportError("No module named 'pyoidn'")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", fake)
    with pytest.raises(MethodError, match=r"needs the pyoidn package \(pip install 'jaxdenoise\[oidn\]'; "
                                                r"from a clone: pip install -e '\.\[oidn\]'\)"):
        jd.denoise(synthetic_frame(), method="oidn")


def test_frame_too_large_for_memory_is_refused_with_xla_estimate(monkeypatch):
    """The program is compiled before it runs; when XLA's estimate exceeds the available memory the
    call fails with the estimate, before any allocation (the limit is lowered here to 1 KiB)."""
    from jaxdenoise import inference

    monkeypatch.setattr(inference, "available_memory", lambda: 1024)
    b = synthetic_frame(h=31, w=17)  # a signature no other test compiled
    with pytest.raises(MethodError, match=r"method 'gaussian': this input \(\(31, 17\)\) needs .* GiB by XLA's "
                                          r"estimate .* more than the 0.0 GiB available"):
        jd.denoise(b, method="gaussian")
    monkeypatch.undo()
    assert jd.denoise(b, method="gaussian").shape == (31, 17, 3)


def test_compiled_once_per_signature():
    from jaxdenoise.inference import inference_fn

    fn = inference_fn(get("gaussian"))
    b = synthetic_frame(h=29, w=13)
    first = fn.compile({}, b)
    again = fn.compile({}, b)
    assert first.compile_seconds > 0 and first.xla_bytes > 0 and first.cache in ("hit", "miss")
    assert again.seconds == 0.0 and again.cache == "memory" and again.xla_bytes == first.xla_bytes  # no 2nd compile


def test_regime_notes_say_where_a_network_runs_outside_what_it_was_trained_on():
    from jaxdenoise.inference import notes
    from jaxdenoise.methods import get

    demc, paper, rae, lbf = get("demc"), get("demc-paper"), get("rae"), get("lbf")
    at = lambda spp: synthetic_frame(8, 8, seed=1).replace(spp=np.float32(spp))
    assert notes(paper, at(4)) == [] and notes(lbf, at(32)) == [] and notes(demc, at(16)) == []  # inside
    assert notes(paper, at(16)) == ["demc-paper was trained at 4 spp; this frame has 16 spp, outside its trained rates"]
    assert notes(demc, at(128)) == ["demc was trained at 1-64 spp; this frame has 128 spp, outside its trained rates"]
    assert notes(lbf, at(128)) == ["lbf was trained at 4-64 spp; this frame has 128 spp, outside its trained rates"]
    single = [n for n in notes(rae, at(1)) if "single frame" in n]
    assert len(single) == 1 and "7-frame sequences" in single[0]
    with_ndc = at(1).replace(world_to_ndc=np.eye(4, dtype=np.float32))
    assert notes(rae, with_ndc, sequence=True) == []  # in a video its state is carried
    # without the camera's projection a video gets no TAA: said
    assert notes(rae, at(1), sequence=True) == ["rae ran without optional buffer(s) ['world_to_ndc'] it can use"]
    assert notes(get("gaussian"), at(1000)) == []  # no trained regime


def test_auto_picks_the_best_method_the_frame_has_buffers_for(monkeypatch):
    from jaxdenoise.api import choose_method

    lbf_frame = synthetic_frame(8, 8, seed=1, fields=("color", "albedo", "albedo2", "normal", "position",
                                                      "visibility")).replace(spp=np.float32(4))
    assert choose_method(lbf_frame) == "demc"  # demc before lbf when both could run
    grad = synthetic_frame(8, 8, seed=1, fields=("color", "albedo", "normal", "depth", "dx", "dy"))
    assert choose_method(grad) == "gradnet"
    plain = synthetic_frame(8, 8, seed=1, fields=("color",))
    assert choose_method(plain) == "oidn"
    # without OIDN's package: the edge-aware filter if the frame has colour variance, never a blur
    from jaxdenoise.methods import oidn
    monkeypatch.setattr(oidn, "requirements", lambda: "no pyoidn", raising=False)
    assert choose_method(synthetic_frame(8, 8, seed=1, fields=("color", "color_var"))) == "bilateral"
    with pytest.raises(MethodError, match=r"method 'auto': no method of .* runs on a frame with \['color'.*install OIDN"):
        choose_method(plain)


def test_a_missing_buffer_is_named_before_weights_load_or_compile(tmp_path, monkeypatch):
    """Every missing buffer and metadata field in one error, before the weights load (the early check
    uses the default config: the shipped weights' configs need exactly what the defaults need)."""
    from jaxdenoise import api
    from jaxdenoise.buffers import BuffersError
    from jaxdenoise.cli import main
    from jaxdenoise.io import write_buffers
    from jaxdenoise.methods import get

    for name in ("lbf", "lbf-nlm", "demc", "rae", "gradnet"):
        assert api.resolve(name)[0].required() == get(name).required(), name
    calls = []
    monkeypatch.setattr(api, "resolve", lambda *a, **k: calls.append(a) or (_ for _ in ()).throw(AssertionError))
    bare = synthetic_frame(8, 8, seed=1, fields=("color",)).replace(spp=None)
    with pytest.raises(BuffersError, match=r"needs buffer\(s\) \['albedo', .*\] and the frame's \['spp'\].*"
                                           r"data_gen render SCENE --methods lbf"):
        jd.denoise(bare, method="lbf")
    write_buffers(tmp_path / "bare.exr", synthetic_frame(8, 8, seed=1, fields=("color",)))
    assert main(["denoise", str(tmp_path / "bare.exr"), "-o", str(tmp_path / "o.exr"), "--method", "demc"]) != 0
    assert calls == []  # neither path reached the weights
