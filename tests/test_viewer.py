"""viewer.html from bench (jaxdenoise.viewer): its data equal results.json; one frame, a sequence and
a failed method all give a valid page; over the size cap the images go to a folder; in headless
Chromium (slow; scripts/setup_browser.sh installs it) every image decodes, switching methods changes
the pixels, and no JavaScript error occurs."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from jaxdenoise import bench, viewer

from conftest import make_shot, registered, synthetic_frame

ROOT = Path(__file__).resolve().parents[1]


def _data(root: Path) -> Path:
    from jaxdenoise.io import write_buffers, write_image

    (root / "scene_0000").mkdir(parents=True)
    make_shot(root / "scene_0000", synthetic_frame(16, 16, seed=1).color * 2,
              {4: synthetic_frame(16, 16, seed=2, fields=("color", "albedo", "normal")),
               16: synthetic_frame(16, 16, seed=3, fields=("color", "albedo", "normal", "dx", "dy"))})
    for t in range(3):
        d = root / "seq" / f"frame_{t:04d}"
        d.mkdir(parents=True)
        write_image(d / "reference.exr", synthetic_frame(16, 16, seed=10 + t).color)
        write_buffers(d / "spp0004_00.exr", synthetic_frame(16, 16, seed=20 + t, fields=("color", "albedo", "normal")))
    return root


def _page_data(html: str) -> dict:
    return json.loads(re.search(r"var DATA = (\{.*?\});\n", html, re.S).group(1))


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    root = tmp_path_factory.mktemp("v")
    data = _data(root / "data")
    with registered("gauss-needs-dx", "fake_needs_dx"):  # runs on the 16-spp frame only: fails on the others
        rep = bench.run(data, ["input", "gaussian", "gauss-needs-dx"], root / "r", runs=5, progress=False)
    return rep, root / "r"


def test_viewer_numbers_equal_results_json(report):
    rep, out = report
    page = _page_data((out / "viewer.html").read_text())
    results = json.loads((out / "results.json").read_text())["records"]
    shown = {(f["file"], m["method"]): m for f in page["frames"] for m in f["methods"] if "failed" not in m}
    assert len(shown) == len(results)
    for r in results:
        m = shown[(r["file"], r["method"])]
        assert (m["relmse"], m["ssim"], m["seconds"]) == (r["relmse"], r["ssim"], r["seconds"])  # exact
    # one frame, a sequence, and a method that failed on some frames: all on the page
    files = {f["file"] for f in page["frames"]}
    assert "scene_0000/spp0004_00.exr" in files and any(f["sequence"] for f in page["frames"])
    failed = [m for f in page["frames"] for m in f["methods"] if "failed" in m]
    assert failed and all("lacks buffer(s) ['dx']" in m["failed"] for m in failed)
    assert any(page["temporal"].values())


def test_images_are_half_floats_of_the_outputs(report):
    import base64

    from jaxdenoise.io import read_image

    rep, out = report
    html = (out / "viewer.html").read_text()
    images = json.loads(re.search(r"var IMAGES = (\{.*?\});\n", html, re.S).group(1))
    rec = next(r for r in rep["records"] if r["method"] == "input" and r["file"] == "scene_0000/spp0004_00.exr")
    im = images[rec["image_id"]]
    px = np.frombuffer(base64.b64decode(im["data"]), "<f2").reshape(im["h"], im["w"], 3)
    src = read_image(out / rep["config"]["data_dir"] / rec["file"])  # the input method's output is the input
    np.testing.assert_allclose(px.astype(np.float32), src, rtol=1e-3, atol=1e-4)  # float16 precision


def test_over_the_cap_images_go_to_a_folder(report, tmp_path):
    rep, out = report
    store = viewer.ImageStore()
    store.add("a", np.ones((4, 4, 3), np.float32))
    rep2 = {"records": [{"file": "x.exr", "shot": "s", "spp": 4, "method": "input", "relmse": 0.1, "ssim": 0.9,
                         "seconds": 0.001, "image_id": "a", "reference_image": "a"}], "skipped": [], "temporal": [],
            "config": {}}
    path = viewer.write_viewer(rep2, store, tmp_path, max_mib=1e-6)
    assert (tmp_path / viewer.IMAGES_DIR).is_dir() and len(list((tmp_path / viewer.IMAGES_DIR).glob("*.js"))) == 1
    assert '<script src="viewer_images/' in path.read_text()


def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    r = subprocess.run(["bash", str(ROOT / "scripts" / "setup_browser.sh")], capture_output=True, text=True)
    for name in ("chromium", "chromium-browser"):
        if shutil.which(name):
            return shutil.which(name)
    pytest.skip(f"no Chromium and it cannot be installed here: {r.stdout.strip()} {r.stderr.strip()}")


def run_selftest(page: Path, screenshot: Path | None = None) -> dict:
    """Open ``page#selftest`` in headless Chromium; return the page's own check results."""
    exe = _chromium()
    flags = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--allow-file-access-from-files",
             "--virtual-time-budget=20000", "--window-size=1400,1000"]
    r = subprocess.run(flags + ["--dump-dom", page.resolve().as_uri() + "#selftest"], capture_output=True,
                       text=True, timeout=180)
    m = re.search(r'<pre id="selftest">(.*?)</pre>', r.stdout, re.S)
    assert m, f"the self-test did not run: {r.stderr[-1500:]}"
    if screenshot is not None:
        subprocess.run(flags + [f"--screenshot={screenshot}", page.resolve().as_uri()], capture_output=True,
                       timeout=180)
    return json.loads(m.group(1).replace("&quot;", '"').replace("&amp;", "&"))


@pytest.fixture(scope="module")
def one_frame(tmp_path_factory):
    root = tmp_path_factory.mktemp("one")
    (root / "data" / "scene_0000").mkdir(parents=True)
    make_shot(root / "data" / "scene_0000", synthetic_frame(16, 16, seed=1).color, {4: synthetic_frame(16, 16, seed=2)})
    bench.run(root / "data", ["input", "gaussian"], root / "r", runs=5, progress=False)
    return root / "r"


def test_a_folder_with_one_frame_gives_a_page(one_frame):
    page = _page_data((one_frame / "viewer.html").read_text())
    assert len(page["frames"]) == 1 and [m["method"] for m in page["frames"][0]["methods"]] == ["input", "gaussian"]


@pytest.mark.slow
@pytest.mark.parametrize("which", ["frames, a sequence and a failure", "one frame"])
def test_viewer_in_headless_chromium(report, one_frame, tmp_path, which):
    out = report[1] if which != "one frame" else one_frame
    res = run_selftest(out / "viewer.html", tmp_path / "shot.png")
    n_images = len(json.loads(re.search(r"var IMAGES = (\{.*?\});\n", (out / "viewer.html").read_text(), re.S).group(1)))
    assert res["errors"] == [] and res["undecoded"] == [] and res["images"] == n_images > 0
    assert res["switch_changes"] is True and res["numbers_ok"] is True
    assert (tmp_path / "shot.png").stat().st_size > 1000
