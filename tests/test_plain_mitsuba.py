"""Plain Mitsuba output gets in: an ``aov`` integrator's film (written by Mitsuba here, 8x6) reads
with its normals, position, depth and albedo; unnamed ``ch00..`` tensors fail saying how to name
them; ``channels=`` / ``--channels`` and ``spp=`` / ``--spp`` map the rest; ``--width``/``--height``
work on an XML that declares no ``resx``/``resy``."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import data_gen
from jaxdenoise import JaxdenoiseWarning, cli
from jaxdenoise.io import ExrError, parse_channels, read_buffers
from jaxdenoise.errors import JaxdenoiseError

AOVS = "albedo:albedo,nn:sh_normal,pp:position,dd:depth,n:geo_normal"


def _scene():
    import mitsuba as mi

    v = data_gen.setup_mitsuba()
    assert v.startswith("llvm"), f"these tests need an LLVM Mitsuba variant; setup_mitsuba() chose {v!r}"
    return mi, mi.load_dict({
        "type": "scene",
        "integrator": {"type": "aov", "aovs": AOVS, "img": {"type": "path", "max_depth": 3}},
        "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 8, "height": 6,
                                                   "rfilter": {"type": "box"}, "component_format": "float32"}},
        "ball": {"type": "sphere", "center": [0, 0, 4], "radius": 3.0, "bsdf": {"type": "diffuse"}},  # fills the view
        "sky": {"type": "constant"}})


@pytest.fixture(scope="module")
def aov_files(tmp_path_factory):
    mi, scene = _scene()
    folder = tmp_path_factory.mktemp("aov")
    tensor = mi.render(scene, spp=4)
    film = folder / "film.exr"
    scene.sensors()[0].film().write(str(film))  # named channels, as `mitsuba scene.xml` writes them
    bare = folder / "bitmap.exr"
    mi.Bitmap(tensor).write(str(bare))  # a bare tensor: ch00..ch16
    return film, bare, np.asarray(tensor)


def test_aov_film_reads_normals_position_depth_albedo(aov_files):
    film, _, tensor = aov_files
    with pytest.warns(JaxdenoiseWarning, match=r"\['n.X', 'n.Y', 'n.Z'\] look like a buffer"):
        b, attrs = read_buffers(film)
    assert {"color", "albedo", "normal", "position", "depth"} <= b.present()
    assert attrs["channels_from"] == {"normal": "nn.X nn.Y nn.Z", "position": "pp.X pp.Y pp.Z", "depth": "dd.T"}
    # what Mitsuba computed, checked by geometry: the camera sits at the origin inside nothing, every
    # pixel sees the ball (centre (0, 0, 4), radius 3); box-filtered over a pixel, so 1e-2 tolerances
    centre = np.array([0, 0, 4], np.float32)
    np.testing.assert_allclose(np.linalg.norm(b.position - centre, axis=-1), 3.0, atol=1e-2)
    np.testing.assert_allclose(b.depth[..., 0], np.linalg.norm(b.position, axis=-1), rtol=1e-2)
    np.testing.assert_allclose(b.normal, (b.position - centre) / 3.0, atol=2e-2)
    assert b.spp is None and "spp" not in attrs  # Mitsuba writes none


def test_explicit_channels_and_spp(aov_files):
    film, _, tensor = aov_files
    with pytest.warns(JaxdenoiseWarning, match=r"\['nn.X', 'nn.Y', 'nn.Z'\] look like"):  # now nn is left
        b, attrs = read_buffers(film, channels={"N": "n", "Z": "dd"}, spp=4)
    assert attrs["channels_from"]["normal"] == "n.X n.Y n.Z"  # the geometric normal, as asked
    assert float(b.spp) == 4 and attrs["channels_from"]["normal"] == "n.X n.Y n.Z"
    for bad, why in (({"Q": "nn"}, "unknown key 'Q'"), ({"N": "zz"}, "no 3-channel layer 'zz'"),
                     ({"R": "nope"}, "maps 'R' to 'nope'"), ({"R": "dd.T"}, "only \\['R'\\]")):
        with pytest.raises(JaxdenoiseError, match=why):
            read_buffers(film, channels=bad)
    with pytest.raises(JaxdenoiseError, match="spp=0"):
        read_buffers(film, spp=0)
    assert parse_channels("N=nn, P=pp,Z=dd") == {"N": "nn", "P": "pp", "Z": "dd"}
    for text in ("N", "N=", "=nn", "N=nn,N=pp"):
        with pytest.raises(JaxdenoiseError, match="--channels"):
            parse_channels(text)


def test_header_spp_conflict_is_an_error(tmp_path):
    import jaxdenoise as jd

    path = jd.write_buffers(tmp_path / "f.exr", jd.Buffers(color=np.ones((2, 3, 3), np.float32), spp=np.float32(4)))
    assert float(read_buffers(path, spp=4)[0].spp) == 4
    with pytest.raises(ExrError, match="spp=16 given, but the header says spp=4"):
        read_buffers(path, spp=16)


def test_bare_tensor_says_how_to_name_its_channels(aov_files):
    _, bare, tensor = aov_files
    with pytest.raises(ExrError, match=r"unnamed \(ch00..ch15.*film\(\)\.write.*--channels R=ch00"):
        read_buffers(bare)
    # the tensor's channels: R G B, then each AOV in order (albedo 3-5, nn 6-8, pp 9-11, dd 12, n 13-15)
    with pytest.warns(JaxdenoiseWarning, match=r"\['ch03', 'ch04', 'ch05', 'ch09'"):  # the rest, named
        b, _ = read_buffers(bare, channels={"R": "ch00", "G": "ch01", "B": "ch02", "N.X": "ch06", "N.Y": "ch07",
                                            "N.Z": "ch08", "Z": "ch12"})
    np.testing.assert_array_equal(b.normal, tensor[..., 6:9])
    np.testing.assert_array_equal(b.depth[..., 0], tensor[..., 12])


def test_cli_denoises_a_plain_mitsuba_film(aov_files, tmp_path, capsys):
    film, _, _ = aov_files
    out = tmp_path / "out.exr"
    assert cli.main(["denoise", str(film), "-o", str(out), "--method", "gaussian", "--spp", "4",
                     "--channels", "N=nn,Z=dd"]) == 0
    cfg = json.loads((tmp_path / "out.config.json").read_text())
    assert cfg["spp"] == 4 and cfg["channels"] == {"N": "nn", "Z": "dd"}
    assert cfg["channels_from"]["position"] == "pp.X pp.Y pp.Z"
    assert "warning:" in capsys.readouterr().err  # n.X is named, as one warning line
    assert cli.main(["denoise", str(film), "-o", str(out), "--channels", "N"]) == 2  # a bad mapping: one error line
    assert "expected e.g. N=nn,P=pp,Z=dd" in capsys.readouterr().err


XML = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 1, 4" target="0, 0.5, 0" up="0, 1, 0"/></transform>
    {film}
  </sensor>
  <bsdf type="diffuse" id="tex"><texture type="bitmap" name="reflectance"><string name="filename" value="tex.exr"/></texture></bsdf>
  <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/><scale value="3"/></transform><ref id="tex"/></shape>
  <shape type="sphere"><point name="center" x="0" y="3" z="0"/><float name="radius" value="0.3"/>
    <emitter type="area"><rgb name="radiance" value="20"/></emitter></shape>
</scene>
"""


def test_width_height_on_an_xml_without_resx_resy(tmp_path, monkeypatch):
    import jaxdenoise as jd
    from data_gen.scenes import SceneError, load_scene

    _scene()
    folder = tmp_path / "scene"
    folder.mkdir()
    jd.write_image(folder / "tex.exr", np.full((4, 4, 3), 0.5, np.float32))  # a relative asset path
    xml = folder / "box.xml"
    xml.write_text(XML.format(film='<film type="hdrfilm"><integer name="width" value="64"/>'
                                   '<integer name="height" value="48"/><rfilter type="box"/></film>'))
    monkeypatch.chdir(tmp_path)  # not the scene's folder: the texture resolves through the XML's own
    scene = load_scene(str(xml), width=13, height=7)
    assert tuple(scene.sensors()[0].film().size()) == (13, 7)
    assert tuple(load_scene(str(xml)).sensors()[0].film().size()) == (64, 48)  # untouched without a size
    assert tuple(load_scene(str(xml), width=20).sensors()[0].film().size()) == (20, 48)
    bare = folder / "nofilm.xml"
    bare.write_text(XML.format(film=""))
    with pytest.raises(SceneError, match=r"need a <film type=\"hdrfilm\"> inside its <sensor>"):
        load_scene(str(bare), width=13, height=7)
