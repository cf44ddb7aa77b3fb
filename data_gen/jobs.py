"""One dataset job: a procedural scene rendered into its shot folder (or a camera fly-through).

`data_gen.dataset` builds the jobs and runs them here, in worker processes or on a Dask cluster
(`data_gen.cluster`); both import this module, and neither imports the other at module level.
"""
from __future__ import annotations

from .shot import render_shot


def render_job(job: dict) -> tuple[str, dict]:
    """Render the shot (or fly-through) a job describes into ``job["dir"]``; ``(name, record)``."""
    from .scenes import build_scene

    scene = build_scene(job["family"], job["scene_seed"], width=job["width"], height=job["height"])
    scene["__name__"] = f"{job['family']}:{job['scene_seed']}"
    if job.get("frames"):  # a camera fly-through: DIR/scene_XXXX/frame_XXXX/ (Chaitanya 2017 Sec. 4.3)
        from .sequences import render_sequence

        seq = render_sequence(scene, job["dir"], n_frames=job["frames"], instances=job["instances"], spp=job["spp"],
                              ref_spp=job["ref_spp"], seed=job["scene_seed"], buffers=job["buffers"],
                              methods=job["methods"], max_depth=job["max_depth"], progress=job["progress"],
                              samples_per_pass=job["samples_per_pass"], shift=job.get("shift"),
                              primal=job.get("primal", "base"))
        rec = {"frames": len(seq["frames"]), "scene": scene["__name__"],
               "render_seconds": float(sum(f.get("render_seconds", 0.0) for f in seq["frames"])),
               "family": scene.get("__family__", job["family"]), "requested_family": job["family"]}
        return job["name"], rec
    rec = render_shot(scene, job["dir"], spp=job["spp"], ref_spp=job["ref_spp"], instances=job["instances"],
                      methods=job["methods"], buffers=job["buffers"], max_depth=job["max_depth"],
                      seed=job["scene_seed"], progress=job["progress"], samples_per_pass=job["samples_per_pass"],
                      shift=job.get("shift"), primal=job.get("primal", "base"), _stop_after=job.get("_stop_after"))
    rec["family"] = scene.get("__family__", job["family"])
    rec["requested_family"] = job["family"]
    return job["name"], rec
