"""The scene library (data_gen/library): the split file, the asset script, every scene loading and
rendering through data_gen with --width/--height honoured, the fly-through cameras staying inside
their scenes, and ``dataset --library``. Renders are 16x12 or smaller at 1-4 spp; rendering every
scene (and its gradient-domain path) is the slow test."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import data_gen
from jaxdenoise.errors import JaxdenoiseError
from data_gen import library
from data_gen.library import make_assets

ROOT = Path(__file__).resolve().parents[1]


def _llvm():
    v = data_gen.setup_mitsuba()
    assert v.startswith("llvm"), f"these tests need an LLVM Mitsuba variant (scripts/setup.sh installs it); got {v!r}"


# --------------------------------------------------------------------------------------------------
# Split file
# --------------------------------------------------------------------------------------------------
def test_split_file_covers_every_scene_exactly_once():
    idx = library.index()
    splits = idx["splits"]
    assert tuple(splits) == library.SPLITS
    names = [n for s in library.SPLITS for n in splits[s]]
    assert len(names) == len(set(names)), "a scene is listed twice"
    for a in library.SPLITS:
        for b in library.SPLITS:
            if a < b:
                assert not set(splits[a]) & set(splits[b]), f"splits {a} and {b} share scenes"
    on_disk = {p.stem for p in library.LIBRARY_DIR.glob("*.xml")}
    assert set(names) == on_disk, "every XML in data_gen/library is in exactly one split, and only those"
    assert all(library.scene_path(n).is_file() for n in names)
    assert len(names) >= 16 and len(splits["eval"]) >= 4 and 1 <= len(splits["val"]) < len(splits["train"])
    assert [library.split_of(n) for n in splits["val"]] == ["val"] * len(splits["val"])


def test_split_file_errors_name_the_problem(tmp_path):
    good = json.loads(library.SPLIT_FILE.read_text())
    bad = json.loads(json.dumps(good))
    bad["splits"]["val"].append(good["splits"]["eval"][0])
    p = tmp_path / "split.json"
    p.write_text(json.dumps(bad))
    with pytest.raises(library.LibraryError, match=f"'{good['splits']['eval'][0]}' is listed in split 'val'"):
        library.index(p)
    bad = json.loads(json.dumps(good))
    del bad["splits"]["val"]
    p.write_text(json.dumps(bad))
    with pytest.raises(library.LibraryError, match="exactly the keys"):
        library.index(p)
    bad = json.loads(json.dumps(good))
    bad["splits"]["train"].append("nowhere")
    bad["scenes"]["nowhere"] = bad["scenes"][good["splits"]["train"][0]]
    for name in good["scenes"]:  # the scene files beside the split file, except nowhere.xml
        (tmp_path / f"{name}.xml").write_bytes(library.scene_path(name).read_bytes())
    p.write_text(json.dumps(bad))
    with pytest.raises(library.LibraryError, match="scene 'nowhere' has no scene file"):
        library.index(p)
    with pytest.raises(library.LibraryError, match="unknown split 'test'"):
        library.scene_names("test")
    with pytest.raises(library.LibraryError, match="no scene named 'nope'.*kitchen"):
        library.scene_path("library:nope")


# --------------------------------------------------------------------------------------------------
# Assets
# --------------------------------------------------------------------------------------------------
def _read_ply(path: Path):
    data = path.read_bytes()
    head, body = data.split(b"end_header\n", 1)
    lines = head.decode().splitlines()
    nv = int(next(l for l in lines if l.startswith("element vertex")).split()[-1])
    nf = int(next(l for l in lines if l.startswith("element face")).split()[-1])
    verts = np.frombuffer(body[:nv * 24], "<f4").reshape(nv, 6)
    faces = np.frombuffer(body[nv * 24:], dtype=[("n", "u1"), ("i", "<i4", (3,))], count=nf)
    assert (faces["n"] == 3).all()
    return verts, faces["i"].astype(np.int64)


def _pixels(path: Path) -> np.ndarray:
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(path))
    assert not buf.has_error, buf.geterror()
    return buf.get_pixels(oiio.FLOAT)


def test_asset_script_reproduces_the_committed_assets(tmp_path):
    """Byte for byte where the libraries match (this machine); else pixels within one 8-bit step
    (PNG), 1e-3 relative (half-float EXR) and 1e-5 (PLY float32 positions/normals, exact indices)."""
    written = make_assets.write_all(tmp_path)
    committed = library.LIBRARY_DIR / "assets"
    rel = sorted(p.relative_to(tmp_path).as_posix() for p in written)
    assert rel == sorted(p.relative_to(committed).as_posix() for p in committed.rglob("*") if p.is_file()), \
        "assets/ holds exactly what make_assets.py writes"
    differ = []
    for r in rel:
        new, old = tmp_path / r, committed / r
        if new.read_bytes() == old.read_bytes():
            continue
        differ.append(r)
        if r.endswith(".ply"):
            (vn, fn), (vo, fo) = _read_ply(new), _read_ply(old)
            assert np.array_equal(fn, fo) and np.allclose(vn, vo, atol=1e-5), r
        elif r.endswith(".png"):
            assert np.abs(_pixels(new) - _pixels(old)).max() <= 1.5 / 255, r
        else:
            a, b = _pixels(new), _pixels(old)
            assert np.allclose(a, b, rtol=1e-3, atol=1e-4), r


def test_scenes_use_only_script_made_assets_and_the_library_is_small():
    made = {p.relative_to(library.LIBRARY_DIR / "assets").as_posix()
            for p in (library.LIBRARY_DIR / "assets").rglob("*") if p.is_file()}
    import xml.etree.ElementTree as ET

    used = set()
    for name in library.scene_names():
        for el in ET.parse(library.scene_path(name)).getroot().iter("string"):
            if el.get("name") == "filename":
                v = el.get("value")
                assert v.startswith("assets/"), f"{name}: {v} is not a library asset"
                used.add(v[len("assets/"):])
    assert used <= made
    assert not made - used, f"assets no scene uses: {sorted(made - used)}"
    size = sum(p.stat().st_size for p in library.LIBRARY_DIR.rglob("*") if p.is_file() and "__pycache__" not in p.parts)
    assert size < 3 * 2**20, f"the library is {size / 2**20:.2f} MiB (budget 3 MiB)"


def test_meshes_are_consistently_oriented():
    """Every triangle's winding agrees with its vertex normals (a dielectric needs outward normals);
    tolerance: strictly positive dot product for every non-degenerate triangle."""
    for name, fn in make_assets.MESHES.items():
        p, n, f = fn().arrays()
        g = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
        area = np.linalg.norm(g, axis=1)
        dots = (g * n[f].mean(1)).sum(1)
        assert (dots[area > 1e-12] > 0).all(), name


@pytest.mark.mitsuba
def test_envmap_sun_lies_where_make_assets_puts_it():
    """Mitsuba's lat-long mapping is the one make_assets.sky_direction inverts: the radiance seen
    towards the configured sun direction is the sun's (within 5 %)."""
    import drjit as dr
    import mitsuba as mi

    data_gen.setup_mitsuba()
    for name, sun in (("sky_day", (0.45, 0.766, -0.46)), ("sky_evening", (-0.85, 0.42, 0.3))):
        em = mi.load_dict({"type": "envmap", "filename": str(library.LIBRARY_DIR / "assets/envmaps" / f"{name}.exr")})
        d = np.asarray(sun, np.float64) / np.linalg.norm(sun)
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wi = mi.Vector3f(*[float(-v) for v in d])
        toward = float(np.asarray(em.eval(si)).max())
        peak = float(_pixels(library.LIBRARY_DIR / "assets/envmaps" / f"{name}.exr").max())
        assert toward == pytest.approx(peak, rel=0.05), name


# --------------------------------------------------------------------------------------------------
# Loading and rendering
# --------------------------------------------------------------------------------------------------
@pytest.mark.mitsuba
def test_every_scene_loads_at_any_size_and_frame0_is_its_own_view():
    """Every scene loads through data_gen at 16x12 and at its default size (declared resx/resy),
    uses a box filter, and its split-file camera target lies on its own viewing axis (tolerance
    1e-4 of the distance), so frame 0 of a fly-through is the scene's view."""
    from data_gen.render import film_size
    from data_gen.sequences import camera_params, camera_positions

    data_gen.setup_mitsuba()
    for name in library.scene_names():
        text = library.scene_path(name).read_text()
        assert 'value="$resx"' in text and 'value="$resy"' in text and '<rfilter type="box"/>' in text, name
        scene = data_gen.load_scene(f"library:{name}", width=16, height=12)
        assert film_size(scene) == (16, 12), name
        assert film_size(data_gen.load_scene(library.scene_path(name))) == library.default_size(name), name
        params = camera_params(scene)
        params.update(library.camera(name))
        o, t, _ = camera_positions(params, 1, seed=0)
        fwd = np.asarray(camera_params(scene)["target"]) - o[0]
        cam = t[0] - o[0]
        assert np.linalg.norm(np.cross(fwd / np.linalg.norm(fwd), cam)) < 1e-4 * np.linalg.norm(cam), name
        assert data_gen.describe(scene)["emitters"] >= 1, name


@pytest.mark.mitsuba
def test_fly_through_cameras_stay_inside_and_look_at_the_content():
    """For seeds 0..5 and paths of 7 and 40 frames (2 and 4 spline keys): the camera never passes
    through geometry on its way from the scene's own camera (a ray from the base origin to every
    frame's origin is unoccluded), keeps 5 cm clear of every surface (26 rays of 5 cm), and its
    central ray hits a surface within 40 m."""
    import mitsuba as mi

    from data_gen.sequences import camera_params, camera_positions

    _llvm()
    dirs = np.array([(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) != (0, 0, 0)],
                    np.float64)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for name in library.scene_names():
        scene = data_gen.load_scene(f"library:{name}", width=8, height=6)
        params = camera_params(scene)
        params.update(library.camera(name))
        base = np.asarray(params["origin"], np.float64)
        origins, targets = [], []
        for seed in range(6):
            for n in (7, 40):
                o, t, _ = camera_positions(params, n, seed)
                origins.append(o)
                targets.append(t)
        o = np.concatenate(origins)
        t = np.concatenate(targets)
        seg = o - base
        dist = np.linalg.norm(seg, axis=1)
        moved = dist > 1e-6
        ray = mi.Ray3f(mi.Point3f(*[mi.Float(np.full(moved.sum(), v, np.float32)) for v in base]),
                       mi.Vector3f(*[mi.Float(c.astype(np.float32)) for c in (seg[moved] / dist[moved, None]).T]))
        ray.maxt = mi.Float(dist[moved].astype(np.float32))
        assert not np.asarray(scene.ray_test(ray)).any(), f"{name}: a fly-through passes through geometry"
        po = np.repeat(o, len(dirs), axis=0)
        pd = np.tile(dirs, (len(o), 1))
        ray = mi.Ray3f(mi.Point3f(*[mi.Float(c.astype(np.float32)) for c in po.T]), mi.Vector3f(*[mi.Float(c.astype(np.float32)) for c in pd.T]))
        ray.maxt = mi.Float(np.full(len(po), 0.05, np.float32))
        assert not np.asarray(scene.ray_test(ray)).any(), f"{name}: a fly-through camera comes within 5 cm of a surface"
        fwd = (t - o) / np.linalg.norm(t - o, axis=1, keepdims=True)
        ray = mi.Ray3f(mi.Point3f(*[mi.Float(c.astype(np.float32)) for c in o.T]), mi.Vector3f(*[mi.Float(c.astype(np.float32)) for c in fwd.T]))
        ray.maxt = mi.Float(np.full(len(o), 40.0, np.float32))
        assert np.asarray(scene.ray_test(ray)).all(), f"{name}: a fly-through frame looks at nothing"


@pytest.mark.mitsuba
def test_cli_renders_library_scenes_at_the_requested_size(tmp_path):
    """Three scenes covering a thin lens + small light, an environment map and a point light; a
    path to a library XML works like library:NAME; --width alone keeps the aspect ratio."""
    from jaxdenoise.io import read_buffers, read_image

    _llvm()
    for scene, size, want in (("library:still_life", ["--width", "16", "--height", "12"], (12, 16)),
                              (str(library.scene_path("garden")), ["--width", "16", "--height", "12"], (12, 16)),
                              ("library:shelf", ["--width", "12"], (16, 12))):
        out = tmp_path / Path(scene).stem.replace(":", "_")
        rc = data_gen_main(["render", scene, *size, "--spp", "2", "--ref-spp", "4", "--out", str(out), "--no-progress"])
        assert rc == 0
        b, attrs = read_buffers(out / "spp0002_00.exr")
        assert b.color.shape[:2] == want and int(attrs["spp"]) == 2
        assert read_image(out / "reference.exr").shape[:2] == want
        assert np.isfinite(np.asarray(b.color)).all() and np.asarray(b.color).mean() > 0
    rec = json.loads((tmp_path / "library_still_life" / "shot.json").read_text())
    assert rec["scene"] == library.scene_label("still_life") and rec["scene_info"]["lens"]


def data_gen_main(argv):
    from data_gen.__main__ import main

    return main(argv)


def test_unknown_library_names_are_clear_errors(tmp_path, capsys):
    data_gen.setup_mitsuba()
    with pytest.raises(data_gen.SceneError, match="no scene named 'kitchn'.*kitchen"):
        data_gen.load_scene("library:kitchn")
    assert data_gen_main(["render", "library:kitchn", "--out", str(tmp_path / "x")]) == 2
    assert "no scene named 'kitchn'" in capsys.readouterr().err
    assert data_gen_main(["dataset", "--library", "test", "--out", str(tmp_path / "y")]) == 2
    assert "unknown split 'test'" in capsys.readouterr().err
    assert data_gen_main(["dataset", "--library", "val", "--family", "rooms", "--out", str(tmp_path / "z")]) == 2
    assert "not both" in capsys.readouterr().err
    with pytest.raises(JaxdenoiseError, match="runs past its end"):
        data_gen.generate_dataset(None, 5, tmp_path / "w", library="val")


@pytest.mark.mitsuba
def test_dataset_renders_a_library_split_resumably(tmp_path):
    """dataset --library val (its first scene, 8x6): the bench layout, the manifest names the
    scene and its split, a re-run renders nothing; with frames, a fly-through of the library
    camera at the requested size."""
    from jaxdenoise.io import read_buffers

    _llvm()
    kw = dict(width=8, height=6, spp=(1, 2), ref_spp=4, count=1, progress=False)
    m = data_gen.generate_dataset(None, out=tmp_path / "d", library="val", **kw)
    first = library.scene_names("val")[0]
    rec = m["scenes"]["scene_0000"]
    assert list(m["scenes"]) == ["scene_0000"]
    assert rec["library_scene"] == first and rec["split"] == "val" and rec["scene"] == library.scene_label(first)
    assert m["runs"][-1]["library"] == "val" and m["runs"][-1]["family"] is None
    d = tmp_path / "d" / "scene_0000"
    assert sorted(p.name for p in d.glob("*.exr")) == ["reference.exr", "spp0001_00.exr", "spp0002_00.exr"]
    assert read_buffers(d / "spp0002_00.exr")[0].color.shape == (6, 8, 3)
    mtimes = {p: p.stat().st_mtime_ns for p in d.glob("*.exr")}
    data_gen.generate_dataset(None, out=tmp_path / "d", library="val", **kw)
    assert {p: p.stat().st_mtime_ns for p in d.glob("*.exr")} == mtimes, "a re-run skips finished files"

    m = data_gen.generate_dataset(None, out=tmp_path / "f", library="val", frames=2, instances=1,
                                  **dict(kw, spp=(1,), width=8, height=None))
    seq = json.loads((tmp_path / "f" / "scene_0000" / "sequence.json").read_text())
    assert seq["camera_params"]["radius"] == library.camera(first)["radius"]
    w, h = library.film_size(first, 8, None)
    for k in range(2):
        b, _ = read_buffers(tmp_path / "f" / "scene_0000" / f"frame_{k:04d}" / "spp0001_00.exr")
        assert b.color.shape == (h, w, 3)
    assert m["scenes"]["scene_0000"]["frames"] == 2


@pytest.mark.slow
@pytest.mark.mitsuba
def test_every_scene_renders_every_buffer_and_its_gradients(tmp_path):
    """Every library scene at 16x12: 2 spp with every buffer it can vary, a 4-spp reference, and
    the gradient-domain buffers (reconnection shift, G-PT primal): right sizes, finite,
    non-negative radiance, not black."""
    from jaxdenoise.io import read_buffers, read_image

    _llvm()
    for name in library.scene_names():
        out = tmp_path / name
        data_gen.render_shot(f"library:{name}", out, spp=(2,), ref_spp=4, width=16, height=12, progress=False)
        b, _ = read_buffers(out / "spp0002_00.exr")
        c = np.asarray(b.color)
        assert c.shape == (12, 16, 3) and np.isfinite(c).all() and (c >= 0).all() and c.mean() > 1e-3, name
        assert b.albedo is not None and b.normal is not None, name
        assert read_image(out / "reference.exr").shape == (12, 16, 3)
        data_gen.render_shot(f"library:{name}", tmp_path / f"{name}_g", spp=(2,), ref_spp=0, width=16, height=12,
                             buffers=["dx", "dy"], shift="reconnect", primal="gpt", progress=False)
        g, _ = read_buffers(tmp_path / f"{name}_g" / "spp0002_00.exr")
        assert np.isfinite(np.asarray(g.dx)).all() and np.isfinite(np.asarray(g.dy)).all(), name
