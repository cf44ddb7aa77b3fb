import numpy as np
import pytest

from jaxdenoise import io
from jaxdenoise.buffers import CHANNELS
from jaxdenoise.io import ExrError, read_buffers, read_header, read_image, read_sequence, write_buffers, write_image

from conftest import synthetic_frame


def test_roundtrip_every_channel(tmp_path):
    b = synthetic_frame(h=5, w=7)
    p = write_buffers(tmp_path / "f.exr", b, {"integrator": "buffers", "max_depth": 3, "seconds": 1.5})
    back, attrs = read_buffers(p)
    assert back.present() == b.present()
    for field in CHANNELS:
        np.testing.assert_array_equal(getattr(back, field), getattr(b, field))  # float32 EXR: exact
    assert float(back.spp) == 4.0
    assert attrs["integrator"] == "buffers" and attrs["max_depth"] == 3 and attrs["seconds"] == 1.5
    h = read_header(p)
    assert h["spp"] == 4 and h["width"] == 7 and h["height"] == 5 and "N.var" in h["channels"]


def test_missing_optional_layers_are_none(tmp_path):
    b = synthetic_frame(fields=("color", "albedo"), camera=False)
    back, _ = read_buffers(write_buffers(tmp_path / "f.exr", b))
    assert back.normal is None and back.dx is None and back.present() == {"color", "albedo", "spp"}
    assert back.world_to_camera is None and back.world_to_ndc is None  # no camera in the header: None


def test_not_exr(tmp_path):
    p = tmp_path / "f.exr"
    p.write_text("hello")
    with pytest.raises(ExrError, match=r"f\.exr: cannot be read as an image"):
        read_buffers(p)
    png = tmp_path / "g.png"
    import OpenImageIO as oiio  # a real image in another format
    out = oiio.ImageOutput.create(str(png))
    out.open(str(png), oiio.ImageSpec(2, 2, 3, "uint8"))
    out.write_image(np.zeros((2, 2, 3), np.uint8))
    out.close()
    with pytest.raises(ExrError, match=r"g\.png: is a png file; expected OpenEXR"):
        read_buffers(png)
    with pytest.raises(ExrError, match=r"nope\.exr: no such file"):
        read_buffers(tmp_path / "nope.exr")


def test_truncated(tmp_path):
    b = synthetic_frame(h=64, w=64)
    p = write_buffers(tmp_path / "f.exr", b)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(ExrError, match=r"f\.exr: .*(truncated|cannot be read)"):
        read_buffers(p)


def test_missing_rgb_and_incomplete_layer(tmp_path):
    z = np.zeros((3, 4, 2), np.float32)
    io._write(tmp_path / "a.exr", ["N.X", "N.Y"], z, None)
    with pytest.raises(ExrError, match=r"a\.exr: layer 'normal' is incomplete: has \['N.X', 'N.Y'\], missing channel\(s\) \['N.Z'\]"):
        read_buffers(tmp_path / "a.exr")
    io._write(tmp_path / "b.exr", ["Z", "vis"], z, None)
    with pytest.raises(ExrError, match=r"b\.exr: missing required channel\(s\) R, G, B"):
        read_buffers(tmp_path / "b.exr")


def test_nan_inf_negative_named_with_counts(tmp_path):
    b = synthetic_frame(h=4, w=4, fields=("color", "normal"))
    c = b.color.copy()
    c[0, 0, 1] = np.nan
    c[1, 1, 1] = np.inf
    c[2, 2, 1] = np.nan
    p = write_buffers(tmp_path / "nan.exr", b.replace(color=c))
    with pytest.raises(ExrError, match=r"nan\.exr: channel 'G' has 2 NaN and 1 Inf pixel\(s\)"):
        read_buffers(p)
    c = b.color.copy()
    c[0, :, 2] = -0.5
    p = write_buffers(tmp_path / "neg.exr", b.replace(color=c))
    with pytest.raises(ExrError, match=r"neg\.exr: channel 'B' has 4 negative radiance pixel\(s\)"):
        read_buffers(p)
    # negative normals are legal
    n = -np.abs(b.normal)
    read_buffers(write_buffers(tmp_path / "n.exr", b.replace(normal=n)))


def test_repair_policy(tmp_path):
    b = synthetic_frame(h=4, w=4, fields=("color",))
    c = b.color.copy()
    c[0, 0, 0] = np.nan
    c[1, 0, 0] = -1.0
    c[2, 0, 2] = -np.inf
    p = write_buffers(tmp_path / "r.exr", b.replace(color=c))
    with pytest.warns(RuntimeWarning, match="repaired"):
        back, attrs = read_buffers(p, repair="zero")
    assert attrs["repaired"] == {"R": 2, "B": 1}
    assert back.color[0, 0, 0] == 0 and back.color[1, 0, 0] == 0 and back.color[2, 0, 2] == 0
    np.testing.assert_array_equal(back.color[3], b.color[3])  # untouched pixels exact
    with pytest.raises(ValueError, match="repair='bogus'"):
        read_buffers(p, repair="bogus")


def test_sequence_and_mismatched_sizes(tmp_path):
    for i in range(3):
        write_buffers(tmp_path / f"f{i}.exr", synthetic_frame(seed=i))
    frames, paths = read_sequence(str(tmp_path / "f*.exr"))
    assert len(frames) == 3 and [p.name for p in paths] == ["f0.exr", "f1.exr", "f2.exr"]
    write_buffers(tmp_path / "f3.exr", synthetic_frame(h=9))
    with pytest.raises(ExrError, match=r"f3\.exr: size 10x9 differs"):
        read_sequence(str(tmp_path / "f*.exr"))
    with pytest.raises(ExrError, match="no files match"):
        read_sequence(str(tmp_path / "zzz*.exr"))


def test_write_image_and_bad_shapes(tmp_path):
    img = np.random.default_rng(0).uniform(size=(3, 5, 3)).astype(np.float32)
    np.testing.assert_array_equal(read_image(write_image(tmp_path / "i.exr", img)), img)
    with pytest.raises(ExrError, match=r"shape \(3, 5, 2\); expected \(H, W, 1\|3\|4\)"):
        write_image(tmp_path / "j.exr", np.zeros((3, 5, 2)))


def test_write_is_atomic_on_failure(tmp_path):
    p = write_image(tmp_path / "keep.exr", np.ones((2, 2, 3), np.float32))
    before = p.read_bytes()
    with pytest.raises(ExrError, match="header attribute 'bad' has type list"):
        write_image(p, np.zeros((2, 2, 3), np.float32), {"bad": [1, 2]})
    assert p.read_bytes() == before and sorted(x.name for x in tmp_path.iterdir()) == ["keep.exr"]


def test_identical_frames_give_identical_files(tmp_path):
    import time

    b = synthetic_frame()
    a = write_buffers(tmp_path / "a.exr", b, {"seed": 1}).read_bytes()
    time.sleep(1.1)  # a write-time stamp in the header would differ after a second
    assert write_buffers(tmp_path / "b.exr", b, {"seed": 1}).read_bytes() == a
