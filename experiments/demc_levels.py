"""A network's colour level and exposure (DEMC, issue 33; RAE, issue 34: checks 3 and "colour and
energy"): does it keep the reference's brightness in every colour channel, at every rate, and does
its output scale with its input's exposure?

1. **Level**: for each method and each frame of each ``--data`` folder at each rate, the box mean
   (15 x 15 px) of the output over that of the reference, per colour channel, median over the pixels
   where the reference's box mean (mean of the channels) is above 1e-3 and the 7-pixel frame border
   is left out. 1.0 = the reference's level. The issue's check asks for surface pixels only
   (depth > 0, not emitters): with ``--masks scene`` (the default) each frame's scene is rebuilt from
   its shot.json record (`data_gen.scenes.scene_from_label`) and `data_gen.render.first_hits` casts
   16 rays per pixel: a pixel counts where every ray hit a shape that emits nothing and no ray in its
   15 x 15 box hit an emitter. **Emitters** apart: per channel, the output's sum over the pixels
   whose rays all hit an area emitter (eroded by one pixel) over the reference's, on frames that show
   one (the check: within 5 %). ``--masks none`` measures every lit pixel (the pages before 0.9.2).
2. **Halo**: pixels whose output (channel mean) is above 4x the reference's largest value in the
   9 x 9 square around them (`jaxdenoise.metrics.halo_pixels`), summed over the frames of a rate: every
   pixel, and (with masks) the surface pixels alone, which issue 34's check counts.
3. **Exposure**: on the first frame of each folder at 4 spp, ``f(k x)`` against ``k f(x)`` for
   ``k`` in 1/16, 1/4, 4, 16: the largest ``|f(k x) - k f(x)|`` over the largest ``|k f(x)|``.

    python experiments/demc_levels.py --data data/library_eval4k,data/heldout --out docs/results/demc_rates

Writes ``demc_levels.json`` and ``demc_levels.md`` into ``--out``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "experiments"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from common import all_measured, box_mean, num, write_study  # noqa: E402

BOX = 15
FLOOR = 1e-3
FACTORS = (1 / 16, 1 / 4, 4.0, 16.0)


def frame_levels(out: np.ndarray, ref: np.ndarray, surface: np.ndarray | None = None) -> list[float]:
    """Per colour channel: median over the lit interior pixels (of ``surface``, an (H, W) bool mask,
    where given) of box(out) / box(ref) (module docstring)."""
    bo, br = box_mean(np.asarray(out, np.float64)), box_mean(np.asarray(ref, np.float64)[..., :3])
    e = BOX // 2
    bo, br = bo[e:-e, e:-e], br[e:-e, e:-e]
    lit = br.mean(-1) > FLOOR
    if surface is not None:
        lit &= surface[e:-e, e:-e]
    if not lit.any():
        raise ValueError("frame_levels: no lit surface pixel inside the frame border")
    return [float(np.median(bo[..., c][lit] / np.maximum(br[..., c][lit], 1e-12))) for c in range(3)]


def scene_of(shot_dir: Path, name: str) -> tuple[str, int, int, tuple | None]:
    """``(scene label, width, height, camera)`` of render ``name`` in ``shot_dir``, from its shot.json
    record; ``camera`` is the frame's camera-to-world matrix (nested tuples) when ``shot_dir`` is a
    frame of a fly-through (``frame_XXXX/`` beside a ``sequence.json``), else None (the scene's own)."""
    record = shot_dir / "shot.json"
    try:
        key = json.loads(record.read_text())["files"][name]["key"]
    except (OSError, KeyError, ValueError) as exc:
        raise SystemExit(f"{record}: no render record for {name} ({exc!r}); measure without masks: --masks none")
    camera, seq = None, shot_dir.parent / "sequence.json"
    if seq.is_file():
        frames = json.loads(seq.read_text()).get("frames", [])
        k = int(shot_dir.name[len("frame_"):]) if shot_dir.name[len("frame_"):].isdigit() else -1
        if not 0 <= k < len(frames) or "to_world" not in frames[k].get("camera", {}):
            raise SystemExit(f"{seq}: no camera for {shot_dir.name} (frames 0-{len(frames) - 1}); "
                             "measure without masks: --masks none")
        camera = tuple(tuple(float(v) for v in row) for row in frames[k]["camera"]["to_world"])
    return key["scene"], int(key["width"]), int(key["height"]), camera


def scene_masks(label: str, width: int, height: int, camera: tuple | None = None) -> dict:
    """``surface`` (pixels whose 16 rays all hit a non-emitting shape, with no emitter ray in their
    `BOX` square) and ``emitter`` (pixels whose rays all hit an area emitter, eroded by one pixel) of
    the scene ``label`` at ``width`` x ``height``, rebuilt by data_gen with its camera moved to
    ``camera`` (a fly-through frame's camera-to-world; None: the scene's own) (module docstring)."""
    from scipy.ndimage import maximum_filter, minimum_filter

    from data_gen.render import first_hits
    from data_gen.scenes import scene_from_label
    from data_gen.sequences import set_camera

    scene = scene_from_label(label, width=width, height=height)
    if camera is not None:
        set_camera(scene, camera)
    hits = first_hits(scene)
    near = maximum_filter(hits["emitter"] > 0, size=BOX, mode="nearest")
    return {"surface": (hits["surface"] >= 1.0) & ~near,
            "emitter": minimum_filter(hits["emitter"] >= 1.0, size=3, mode="constant")}


def emitter_level(out: np.ndarray, ref: np.ndarray, emitter: np.ndarray) -> list[float] | None:
    """Per colour channel: the output's sum over the ``emitter`` pixels over the reference's; None
    where the frame shows no emitter."""
    if not emitter.any():
        return None
    o, r = np.asarray(out, np.float64)[emitter], np.asarray(ref, np.float64)[..., :3][emitter]
    return [float(o[:, c].sum() / max(r[:, c].sum(), 1e-12)) for c in range(3)]


def _trained_for(folder: str) -> str:
    """The method a weights folder was trained for (its config.json's ``method``; demc for older ones)."""
    return json.loads((Path(folder) / "config.json").read_text()).get("method", "demc")


def measure(methods: list[str], folders: list[str], spps: list[int], masks: str = "scene") -> dict:
    from jaxdenoise import metrics
    from jaxdenoise.api import resolve
    from jaxdenoise.data import discover, renders_by_spp
    from jaxdenoise.inference import inference_fn, prepare
    from jaxdenoise.io import read_buffers, read_image

    res = {"box": BOX, "floor": FLOOR, "spps": spps, "folders": folders, "methods": {}, "masks": masks}
    cache: dict = {}

    def masks_of(render) -> dict | None:
        if masks == "none":
            return None
        k = scene_of(render.path.parent, render.path.name)  # every rate of a shot: one scene (and camera), one mask
        if k not in cache:
            cache[k] = scene_masks(*k)
        return cache[k]

    for entry in methods:
        name, _, weights = entry.partition("=")  # "demc" or "LABEL=WEIGHTS_FOLDER" (its config names the method)
        m, params = resolve(_trained_for(weights) if weights else name, weights or None)
        fn = inference_fn(m)
        rec = {"config": {k: v for k, v in dataclasses.asdict(m.config).items() if k in ("exposure", "train_spps")},
               "levels": {}, "exposure": {}}
        rec["scores"], rec["halo"], rec["emitters"] = {}, {}, {}
        for folder in folders:
            per_rate, scores, halos, emitters, surface_halos = {}, {}, {}, {}, {}
            for shot in discover(folder):
                ref = read_image(shot.reference)
                for spp, renders in sorted(renders_by_spp(shot, set(spps)).items()):
                    b, _ = read_buffers(renders[0].path)
                    y = np.asarray(fn(params, prepare(m, b)))
                    mk = masks_of(renders[0])
                    per_rate.setdefault(str(spp), []).append(frame_levels(y, ref, mk and mk["surface"]))
                    if mk is not None:
                        emitters.setdefault(str(spp), []).append(emitter_level(y, ref, mk["emitter"]))
                    halos.setdefault(str(spp), []).append(metrics.halo_pixels(y, ref[..., :3]))
                    if mk is not None:
                        surface_halos.setdefault(str(spp), []).append(
                            metrics.halo_pixels(y, ref[..., :3], mk["surface"]))
                    scores.setdefault(str(spp), []).append([float(metrics.relmse(y, ref[..., :3])),
                                                            float(metrics.ssim(y, ref[..., :3]))])
                    if spp == 4 and folder not in rec["exposure"]:
                        base = y.astype(np.float64)
                        worst = 0.0
                        for k in FACTORS:
                            scaled = b.replace(color=np.asarray(b.color) * np.float32(k))
                            yk = np.asarray(fn(params, prepare(m, scaled)), np.float64)
                            worst = max(worst, float(np.max(np.abs(yk - k * base)) / np.max(np.abs(k * base))))
                        rec["exposure"][folder] = {"frame": str(renders[0].path.relative_to(Path(folder).parent)),
                                                   "factors": list(FACTORS), "max_rel_diff": worst}
            rec["levels"][folder] = per_rate
            rec["scores"][folder] = scores
            rec["halo"][folder] = halos
            if masks != "none":
                rec.setdefault("halo_surface", {})[folder] = surface_halos
                rec["emitters"][folder] = emitters
            print(name, folder, {s: np.round(np.median(v, 0), 3).tolist() for s, v in per_rate.items()}, flush=True)
        res["methods"][name] = rec
    return res


def page(res: dict) -> str:
    lines = ["# Colour level and exposure: " + ", ".join(f"`{n}`" for n in res["methods"]), "",
             f"Level = box mean ({res['box']}x{res['box']} px) of the output over the reference's, per channel, "
             f"median over the pixels where the reference's box mean is above {res['floor']:g} (frame border "
             "left out); per rate the median over frames, and the frame furthest from 1 (issue 33 asks for "
             "every channel within 3 % of 1). "
             + ("Surface pixels only: the 16 rays per pixel of `data_gen.render.first_hits` on the frame's "
                "rebuilt scene all hit a shape that emits nothing, and none in the pixel's box hit an emitter. "
                "*Emitters*: output over reference summed over the pixels whose rays all hit an area emitter "
                "(eroded by a pixel), R/G/B, median over the frames that show one (issue 33: within 5 %)."
                if res.get("masks") == "scene" else
                "Emitters are counted with the surfaces (no emitter mask in these frames).")
             + (" RelMSE and SSIM (docs/metrics.md): means over the same frames."
                if all("scores" in r for r in res["methods"].values()) else ""), ""]
    for folder in res["folders"]:
        scored = all("scores" in rec for rec in res["methods"].values())  # (older runs recorded levels only)
        halo = all("halo" in rec for rec in res["methods"].values())
        lit_masks = all(folder in rec.get("halo_surface", {}) for rec in res["methods"].values())
        lit = all(folder in rec.get("emitters", {}) for rec in res["methods"].values())
        lines += [f"## `{folder}`", "", "| method | spp | frames | R | G | B | furthest frame (channel) |"
                  + (" RelMSE | SSIM |" if scored else "")
                  + ((" halo px (surface) |" if lit_masks else " halo px |") if halo else "")
                  + (" emitters R/G/B (frames) |" if lit else ""),
                  "|---|---:|---:|---:|---:|---:|---:|" + ("---:|---:|" if scored else "") + ("---:|" if halo else "")
                  + ("---:|" if lit else "")]
        for name, rec in res["methods"].items():
            for spp, frames in sorted(rec["levels"][folder].items(), key=lambda kv: int(kv[0])):
                lv = np.asarray(frames)
                med = np.median(lv, 0)
                far = lv.flat[int(np.argmax(np.abs(lv - 1.0)))]
                row = (f"| {name} | {spp} | {len(frames)} | {num(med[0], '.3f')} | {num(med[1], '.3f')} | "
                       f"{num(med[2], '.3f')} | {num(far, '.3f')} |")
                if scored:
                    sc = np.mean(rec["scores"][folder][spp], 0)
                    row += f" {num(float(sc[0]), '.4f')} | {num(float(sc[1]), '.3f')} |"
                if halo:
                    on = rec.get("halo_surface", {}).get(folder)
                    row += f" {sum(rec['halo'][folder][spp])}" + (f" ({sum(on[spp])})" if on else "") + " |"
                if lit:
                    shown = [e for e in rec["emitters"][folder][spp] if e is not None]
                    row += (" " + "/".join(num(float(v), ".3f") for v in np.median(shown, 0))
                            + f" ({len(shown)}) |" if shown else " - (0) |")
                lines.append(row)
        lines.append("")
    lines += ["## Exposure", "", "`max |f(k x) - k f(x)| / max |k f(x)|` over k in "
              + ", ".join(f"{k:g}" for k in FACTORS) + " on one 4-spp frame per folder.", "",
              "| method | exposure setting | folder | frame | max relative difference |", "|---|---|---|---|---:|"]
    for name, rec in res["methods"].items():
        for folder, e in rec["exposure"].items():
            lines.append(f"| {name} | {rec['config'].get('exposure', '-')} | `{folder}` | `{e['frame']}` | "
                         f"{num(e['max_rel_diff'], '.2e')} |")
    lines += ["", "Command: `" + res["command"] + "`", ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="comma-separated data_gen folders")
    ap.add_argument("--methods", default="demc,demc-paper",
                    help="comma-separated method names, or LABEL=FOLDER for a demc weights folder (a run's best/)")
    ap.add_argument("--spps", default="1,4,16,64")
    ap.add_argument("--masks", default="scene", choices=("scene", "none"),
                    help="scene: surface pixels and emitters apart, from each frame's rebuilt scene; none: every "
                    "lit pixel")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    res = measure(args.methods.split(","), args.data.split(","), [int(s) for s in args.spps.split(",")],
                  masks=args.masks)
    res["command"] = "python experiments/demc_levels.py " + " ".join(argv if argv is not None else sys.argv[1:])
    all_measured(res, "demc_levels.json")
    print(write_study(Path(args.out), "demc_levels.json", "demc_levels.md", res, page))


if __name__ == "__main__":
    main()
