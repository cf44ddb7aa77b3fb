"""Camera fly-through sequences (`data_gen.sequences`)."""
from __future__ import annotations

import numpy as np
import pytest

from data_gen.sequences import camera_path, camera_positions

PARAMS = {"origin": [0.0, 1.0, 4.0], "target": [0.0, 0.5, 0.0], "up": [0.0, 1.0, 0.0],
          "radius": 0.6, "target_radius": 0.2}


def test_path_starts_at_base_camera_and_is_deterministic():
    o, t, up = camera_positions(PARAMS, 40, seed=3)
    assert o.shape == (40, 3) and t.shape == (40, 3)
    # Tolerance: exact (frame 0 is the first spline key, the base camera).
    assert np.array_equal(o[0], PARAMS["origin"]) and np.array_equal(t[0], PARAMS["target"])
    o2, t2, _ = camera_positions(PARAMS, 40, seed=3)
    assert np.array_equal(o, o2) and np.array_equal(t, t2)
    o3, _, _ = camera_positions(PARAMS, 40, seed=4)
    assert not np.allclose(o, o3)
    # Key points lie within `radius` of the base camera and the spline's overshoot is bounded:
    # tolerance 2 x radius (the cubic's weights have absolute sum <= 1.25 and a reflected phantom
    # key lies within 3 r, so the path stays within 1.375 r).
    assert np.linalg.norm(o - PARAMS["origin"], axis=1).max() <= 2 * PARAMS["radius"]
    assert np.linalg.norm(t - PARAMS["target"], axis=1).max() <= 2 * PARAMS["target_radius"]


def _second_diff(x):
    return np.linalg.norm(x[2:] - 2 * x[1:-1] + x[:-2], axis=1)


def test_path_is_smooth():
    """Bounded second differences. On a segment of a uniform Catmull-Rom spline,
    p''(u) = (2 P0 - 5 P1 + 4 P2 - P3) + 3 u (-P0 + 3 P1 - 3 P2 + P3); both coefficient sets sum to
    0, so the P_i may be replaced by their offsets from the base point: |offset| <= r for keys and
    <= 3 r for a reflected phantom key (2 P0 - P1), which gives |p''| <= (2*3 + 5 + 4 + 1) r +
    3 (3 + 3 + 3 + 1) r = 46 r per unit of spline parameter, hence |second difference| <= 46 r h^2
    (h = parameter step per frame). Smoothness also shows as scaling: doubling the frame count over
    the same keys divides the largest second difference by ~4 (tolerance: by more than 3; a
    piecewise-linear path gives ~2) and the largest step by ~2 (tolerance: 1.5 to 2.5)."""
    n_keys = 5
    params = dict(PARAMS, n_keys=n_keys)
    for n in (32, 64):
        o, t, _ = camera_positions(params, n, seed=7)
        h = (n_keys - 1) / (n - 1)
        assert _second_diff(o).max() <= 46 * PARAMS["radius"] * h * h
        assert _second_diff(t).max() <= 46 * PARAMS["target_radius"] * h * h
    o32, _, _ = camera_positions(params, 32, seed=7)
    o64, _, _ = camera_positions(params, 64, seed=7)
    assert _second_diff(o32).max() / _second_diff(o64).max() > 3.0
    step32 = np.linalg.norm(np.diff(o32, axis=0), axis=1).max()
    step64 = np.linalg.norm(np.diff(o64, axis=0), axis=1).max()
    assert 1.5 < step32 / step64 < 2.5
    # The control: the key points themselves, visited one per frame, are far from smooth.
    keys = o32[:: (32 - 1) // (n_keys - 1)][:n_keys]
    assert _second_diff(keys).max() > 46 * PARAMS["radius"] * ((n_keys - 1) / (32 - 1)) ** 2


def test_transforms_are_rigid_look_at():
    frames = camera_path(PARAMS, 12, seed=1)
    o, t, _ = camera_positions(PARAMS, 12, seed=1)
    assert len(frames) == 12
    for i, tr in enumerate(frames):
        m = np.asarray(tr.matrix, dtype=np.float64).reshape(4, 4)
        r = m[:3, :3]
        # Tolerance 1e-5: float32 transforms.
        assert np.allclose(r.T @ r, np.eye(3), atol=1e-5)
        assert np.allclose(m[:3, 3], o[i], atol=1e-5)
        fwd = (t[i] - o[i]) / np.linalg.norm(t[i] - o[i])
        assert np.allclose(m[:3, 2], fwd, atol=1e-5)
    assert len(camera_path(PARAMS, 1, seed=0)) == 1


def test_bad_input_raises():
    with pytest.raises(ValueError, match="n_frames"):
        camera_positions(PARAMS, 0, seed=0)
    with pytest.raises(ValueError, match="seed"):
        camera_positions(PARAMS, 4, seed=-1)
    with pytest.raises(ValueError, match="target"):
        camera_positions({"origin": [0, 0, 0]}, 4, seed=0)
    with pytest.raises(ValueError, match="origin"):
        camera_positions({"origin": [0, 0], "target": [0, 0, 1]}, 4, seed=0)
    with pytest.raises(ValueError, match="coincide"):
        camera_positions({"origin": [0, 0, 1], "target": [0, 0, 1]}, 4, seed=0)
    with pytest.raises(ValueError, match="up"):
        camera_positions({"origin": [0, 0, 0], "target": [0, 1, 0], "up": [0, 1, 0], "radius": 0.0,
                          "target_radius": 0.0}, 4, seed=0)
    with pytest.raises(TypeError, match="scene_params"):
        camera_positions([0, 0, 0], 4, seed=0)


@pytest.mark.mitsuba
def test_camera_params_frame0_is_the_scene_camera():
    from data_gen.scenes import default_scene, load_scene
    from data_gen.sequences import camera_params

    scene = load_scene(default_scene(width=8, height=8))
    frames = camera_path(camera_params(scene), 5, seed=2)
    m0 = np.asarray(frames[0].matrix, dtype=np.float64).reshape(4, 4)
    ms = np.asarray(scene.sensors()[0].world_transform().matrix, dtype=np.float64).reshape(4, 4)
    assert np.allclose(m0, ms, atol=1e-5)  # tolerance: float32 transforms
    m4 = np.asarray(frames[4].matrix, dtype=np.float64).reshape(4, 4)
    assert not np.allclose(m4, ms, atol=1e-3)  # the camera does move


@pytest.mark.mitsuba
def test_render_sequence_layout_and_resume(tmp_path):
    """3 frames x 2 noisy 1-spp instances + one reference each, in the bench layout; frames see
    different views; instances are independent; a re-run renders nothing; the scene's sensor is put
    back."""
    from data_gen.scenes import default_scene, load_scene
    from data_gen.sequences import render_sequence, set_camera
    from jaxdenoise.io import read_buffers, read_image

    scene = load_scene(default_scene(width=8, height=8))
    before = np.asarray(scene.sensors()[0].world_transform().matrix).copy()
    out = tmp_path / "seq"
    rec = render_sequence(scene, out, n_frames=3, instances=2, spp=1, ref_spp=16, seed=0,
                          buffers=["color", "albedo", "dx", "dy"], progress=False)
    assert len(rec["frames"]) == 3 and (out / "sequence.json").is_file()
    refs = []
    for k in range(3):
        d = out / f"frame_{k:04d}"
        assert sorted(p.name for p in d.glob("*.exr")) == ["reference.exr", "spp0001_00.exr", "spp0001_01.exr"]
        refs.append(read_image(d / "reference.exr"))
        a, attrs = read_buffers(d / "spp0001_00.exr")
        b, _ = read_buffers(d / "spp0001_01.exr")
        assert int(attrs["spp"]) == 1
        assert a.dx is not None and a.dy is not None and a.albedo is not None
        assert not np.array_equal(np.asarray(a.color), np.asarray(b.color))  # independent instances
    # Consecutive frames see different views (tolerance: any difference).
    assert not np.array_equal(refs[0], refs[2])
    assert np.array_equal(np.asarray(scene.sensors()[0].world_transform().matrix), before)
    mtimes = {p: p.stat().st_mtime_ns for p in out.rglob("*.exr")}
    render_sequence(scene, out, n_frames=3, instances=2, spp=1, ref_spp=16, seed=0,
                    buffers=["color", "albedo", "dx", "dy"], progress=False)
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*.exr")} == mtimes
    with pytest.raises(ValueError, match="n_frames"):
        render_sequence(scene, out, n_frames=0)
    # a frame's camera in sequence.json, set on the scene, is the camera its EXRs were rendered with
    # (their world-to-camera, whose x axis OpenEXR's convention flips)
    set_camera(scene, rec["frames"][2]["camera"]["to_world"])
    m = np.asarray(scene.sensors()[0].world_transform().matrix, dtype=np.float64).reshape(4, 4)
    c, _ = read_buffers(out / "frame_0002" / "spp0001_00.exr")
    assert not np.allclose(m, before, atol=1e-3)
    np.testing.assert_allclose(np.diag([-1.0, 1, 1, 1]) @ np.linalg.inv(m), c.world_to_camera, atol=1e-4)


@pytest.mark.mitsuba
def test_render_sequence_sets_the_film_size(tmp_path):
    """width/height reach every frame (a dict or XML scene is loaded at that size)."""
    from data_gen.scenes import default_scene
    from data_gen.sequences import render_sequence
    from jaxdenoise.io import read_buffers

    rec = render_sequence(default_scene(width=8, height=8), tmp_path / "seq", n_frames=2, instances=1, spp=1,
                          ref_spp=2, seed=0, buffers=["color"], progress=False, width=6, height=4)
    assert [(f["width"], f["height"]) for f in rec["frames"]] == [(6, 4), (6, 4)]
    b, _ = read_buffers(tmp_path / "seq" / "frame_0001" / "spp0001_00.exr")
    assert b.color.shape == (4, 6, 3)
    from data_gen.scenes import load_scene

    with pytest.raises(ValueError, match="keeps its film size"):
        render_sequence(load_scene(default_scene(width=8, height=8)), tmp_path / "x", n_frames=1, width=6)
