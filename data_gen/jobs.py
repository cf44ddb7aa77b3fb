"""One dataset job: a procedural or scene-library scene rendered into its shot folder (or a camera
fly-through).

`data_gen.dataset` builds the jobs and runs them here, in worker processes or on a Dask cluster
(`data_gen.cluster`); both import this module, and neither imports the other at module level.
"""
from __future__ import annotations

from .shot import render_shot


def render_job(job: dict) -> tuple[str, dict]:
    """Render the shot (or fly-through) a job describes into ``job["dir"]``; ``(name, record)``.

    A procedural job names ``family`` and ``scene_seed``; a library job names ``library`` (a scene
    of `data_gen.library`, rendered at ``width`` x ``height``, or at its own size where both are
    None, one alone keeping its aspect ratio; its fly-throughs follow the library's camera)."""
    from .scenes import build_scene

    size = {"width": job["width"], "height": job["height"]}
    if job.get("library"):
        from .library import PREFIX, film_size, scene_label, split_of

        size = dict(zip(("width", "height"), film_size(job["library"], job["width"], job["height"])))
        scene = f"{PREFIX}{job['library']}"
        label = scene_label(job["library"])
        about = {"library_scene": job["library"], "split": split_of(job["library"])}
    else:
        scene = build_scene(job["family"], job["scene_seed"], **size)
        scene["__name__"] = label = f"{job['family']}:{job['scene_seed']}"
        size = {}  # already in the scene dict
        about = {"family": scene.get("__family__", job["family"]), "requested_family": job["family"]}
    common = dict(spp=job["spp"], ref_spp=job["ref_spp"], instances=job["instances"], buffers=job["buffers"],
                  methods=job["methods"], max_depth=job["max_depth"], progress=job["progress"],
                  samples_per_pass=job["samples_per_pass"], shift=job.get("shift"), primal=job.get("primal", "base"),
                  gradient_emission=job.get("gradient_emission", "separate"),
                  seed=job["scene_seed"], **size)
    if job.get("frames"):  # a camera fly-through: DIR/scene_XXXX/frame_XXXX/ (Chaitanya 2017 Sec. 4.3)
        from .sequences import render_sequence

        seq = render_sequence(scene, job["dir"], n_frames=job["frames"], **common)
        rec = {"frames": len(seq["frames"]), "scene": label,
               "render_seconds": float(sum(f.get("render_seconds", 0.0) for f in seq["frames"])), **about}
        return job["name"], rec
    rec = render_shot(scene, job["dir"], _stop_after=job.get("_stop_after"), **common)
    rec.update(about)
    return job["name"], rec
