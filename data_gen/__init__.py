"""data_gen: Mitsuba 3 + Dr.Jit renders with every buffer the denoisers use (docs/architecture.md, issue 3).

Public API (the demo and the experiments code against it):

- `setup_mitsuba` picks a working Mitsuba variant (LLVM >= 16, else ``scalar_rgb``);
- `default_scene` a small built-in scene dict; `build_scene` procedural families;
- `render_shot` noisy renders + reference of one shot in the bench layout (resumable);
- `render_sequence` camera fly-through sequences (`data_gen.sequences`); `generate_dataset` many
  procedural scenes;
- `render_buffers` / `render_reference` the arrays themselves, without writing files; `render_frame`
  one frame as `jaxdenoise.Buffers` in memory (what `render_shot` would write);
- `bridge`: Mitsuba tensors to `Buffers` (`buffers_from_tensor`) and `differentiable`, a JAX denoiser
  Dr.Jit's AD calls and differentiates through (inside ``mi.render``'s optimisation loop);
- `library`: the scene library (hand-written XML scenes, their split into train / val / eval, and
  their fly-through cameras); its scenes are named ``library:<name>`` wherever a scene is taken.
"""
from .integrator import FEATURES, PathSettings, derive_seed
from .mitsuba_setup import setup_mitsuba
from .render import render_buffers, render_reference
from .scenes import ALL_FAMILIES, FAMILIES, SceneError, build_scene, default_scene, describe, load_scene
from .shot import plan_buffers, render_frame, render_shot
from .dataset import generate_dataset
from .sequences import camera_path, render_sequence  # written by the gradient/sequences worker
from . import bridge, library
from .bridge import buffers_from_tensor, differentiable

__all__ = [
    "ALL_FAMILIES", "FAMILIES", "FEATURES", "PathSettings", "SceneError", "bridge", "buffers_from_tensor", "build_scene", "camera_path",
    "default_scene", "derive_seed", "describe", "differentiable", "generate_dataset", "library", "load_scene", "plan_buffers",
    "render_buffers", "render_frame", "render_reference", "render_sequence", "render_shot", "setup_mitsuba",
]
