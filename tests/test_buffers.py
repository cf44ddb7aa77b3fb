import jax
import numpy as np
import pytest

from jaxdenoise.buffers import CHANNELS, Buffers, BuffersError, stack

from conftest import synthetic_frame


def test_missing_layers_are_none_and_not_leaves():
    b = Buffers(color=np.zeros((4, 5, 3), np.float32))
    assert b.albedo is None and b.present() == {"color"}
    assert len(jax.tree_util.tree_leaves(b)) == 1


def test_wrong_channel_count_names_field():
    with pytest.raises(BuffersError, match=r"'normal' has 2 channel\(s\); expected 3"):
        Buffers(color=np.zeros((4, 5, 3)), normal=np.zeros((4, 5, 2)))


def test_mismatched_grid_names_both_fields():
    with pytest.raises(BuffersError, match=r"'depth' has pixel grid \(4, 6\) but 'color' has \(4, 5\)"):
        Buffers(color=np.zeros((4, 5, 3)), depth=np.zeros((4, 6, 1)))


def test_required_and_needs_errors():
    b = Buffers(color=np.zeros((2, 2, 3)))
    with pytest.raises(BuffersError, match=r"missing required buffer\(s\) \['albedo'\]"):
        b.validate(("color", "albedo"))
    with pytest.raises(BuffersError, match=r"method 'x' needs buffer\(s\) \['dx', 'dy'\]"):
        b.check_needs({"color", "dx", "dy"}, "x")


def test_pytree_roundtrip_through_jit():
    b = synthetic_frame(fields=("color", "albedo", "depth"))
    out = jax.jit(lambda x: jax.tree_util.tree_map(lambda a: a * 2, x))(b)
    assert isinstance(out, Buffers) and out.normal is None
    np.testing.assert_allclose(out.albedo, 2 * b.albedo, rtol=0, atol=0)  # exact


def test_batched_and_stack():
    frames = [synthetic_frame(seed=s, fields=("color", "normal")) for s in range(3)]
    s = stack(frames)
    assert s.color.shape == (3, 8, 10, 3) and s.spp.shape == (3,)
    with pytest.raises(BuffersError, match="frame 1 has buffers"):
        stack([frames[0], synthetic_frame(fields=("color",))])


def test_only_keeps_color_and_named():
    b = synthetic_frame()
    o = b.only({"albedo"})
    assert o.present() == {"color", "albedo", "spp", "world_to_camera"}  # metadata is never dropped
    assert o.spp == b.spp and o.world_to_camera is b.world_to_camera


def test_channel_table_is_consistent():
    names = [c for chans in CHANNELS.values() for c in chans]
    assert len(names) == len(set(names))


def test_with_variances():
    from jaxdenoise.buffers import with_variances

    assert with_variances({"color", "normal", "dx"}) == {"color", "color_var", "normal", "normal_var", "dx"}
