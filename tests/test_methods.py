"""The method surface (jaxdenoise/methods/protocol.py), checked for every registered method, and the
batch convention: a leading axis on `apply`'s input is a batch of independent frames."""
from __future__ import annotations

import types

import jax
import numpy as np
import pytest

from jaxdenoise.methods import get, names
from jaxdenoise.methods.protocol import Causal, MethodModule, check_module

from conftest import synthetic_frame


@pytest.mark.parametrize("name", names())
def test_registered_method_satisfies_the_surface(name):
    m = get(name)
    assert isinstance(m.module, MethodModule), name
    assert check_module(m.module) == []
    assert m.temporal in ("causal", "windowed", "frame")
    assert "color" in m.needs() and m.required() <= m.needs()


def test_check_module_names_incomplete_hook_groups():
    fake = types.ModuleType("fake_method")
    fake.Config = object
    fake.needs = fake.init = fake.apply = lambda *a: None
    assert check_module(fake) == []
    fake.step = lambda *a: None  # causal without init_state
    problems = check_module(fake)
    assert problems == ["fake_method: causal hooks incomplete: has ['step'], lacks ['init_state']"]
    assert not isinstance(fake, Causal)
    del fake.apply
    assert "fake_method: missing required 'apply'" in check_module(fake)


# Small settings where the defaults would compile large windows (the batch rule does not depend on
# them).
SMALL = {"lbf": {"radius": 1, "prefilter": False}, "lbf-nlm": {"radius": 1, "prefilter": False},
         "bilateral": {"radius": 2, "prefilter": False}, "nlm": {"radius": 2, "prefilter": False}}
# Checked by the energy they minimise instead of pixel by pixel: an L1 solve stops on the L1 energy's
# flat bottom, so two compilations of the same arithmetic (a frame alone, the same frame in a batch of
# two) can land on different points of it (measured with the IRLS solver: pixels 2e-2 apart, energies
# 1.6e-5 relative apart).
BY_ENERGY = {"poisson-l1": "l1"}


# The convolutional networks' batch check compiles a full network twice (10-16 s each): under `slow`.
NETWORKS = ("demc", "demc-paper", "rae", "rae-paper", "gradnet")


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in NETWORKS else n for n in names()])
def test_leading_axis_is_a_batch_of_independent_frames(name):
    from jaxdenoise.api import resolve
    from jaxdenoise.inference import prepare

    m, params = resolve(name) if get(name).requirements() is None else (None, None)
    if m is None:
        pytest.skip(f"{name} cannot run here: {get(name).requirements()}")
    if name in SMALL:
        m = m.with_config(**SMALL[name])
    frames = [prepare(m, synthetic_frame(12, 12, seed=s, spp=4 * (s + 1))) for s in range(2)]
    one = [np.asarray(m.apply(params, f)) for f in frames]
    batch = jax.tree_util.tree_map(lambda *xs: np.stack(xs), *frames)
    out = np.asarray(m.apply(params, batch))
    assert out.shape == (2, 12, 12, 3)  # exact
    if name in BY_ENERGY:
        from jaxdenoise.solvers.poisson import energy

        for f, alone, batched in zip(frames, one, out):
            e = [float(energy(x, f.color, f.dx, f.dy, m.config.alpha, norm=BY_ENERGY[name])) for x in (alone, batched)]
            assert e[1] == pytest.approx(e[0], rel=1e-4)  # each frame's minimum, whether alone or in a batch
        # and the other solver (ADMM, a fixed iteration count) pixel by pixel, as before
        m = m.with_config(solver="admm")
        one = [np.asarray(m.apply(params, f)) for f in frames]
        np.testing.assert_allclose(np.asarray(m.apply(params, batch)), np.stack(one), atol=1e-5, rtol=1e-5)
        return
    # Tolerance 1e-5 absolute: the same float32 arithmetic, compiled once per frame or in a loop body.
    np.testing.assert_allclose(out, np.stack(one), atol=1e-5, rtol=1e-5)
