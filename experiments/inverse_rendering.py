"""Inverse rendering with a denoiser in the loss (issue 39): recover a diffuse albedo, a roughness and
an emitter's intensity by gradient descent, through `data_gen.differentiable`, against wall time.

Two scenes at ``--size`` px (default 64): the embedded default scene (left wall albedo, the gold
sphere's GGX roughness, the ceiling light's radiance) and Mitsuba's Cornell box with a rough copper
box (red wall albedo, the box's roughness, the light's radiance). The target is a ``--target-spp``
render with the true parameters; every run starts from the same wrong parameters (grey albedo 0.4,
half the light, roughness 0.5) and takes Adam steps for ``--budget`` seconds of wall time (Mitsuba's ``mi.ad.Adam``, lr
``--lr``) on the RelMSE between the target and

- ``raw``: the ``prb`` render at ``spp`` (1, 4, 16),
- ``<method>``: that render denoised by a differentiable method (`gaussian`, `demc`, `lbf` from 4 spp:
  it reads variances), its auxiliary buffers from a detached pass of data_gen's integrator at the same
  spp each step (counted in the time),
- ``raw`` at ``--ref-spp`` (64) for ``--ref-budget`` seconds (90): the reference, where a less noisy
  loss gets with more time (the raw loss's gradient is unbiased: PRB takes it from samples
  independent of the primal's, so its optimum is the truth up to the target's own noise).

Recorded per step: wall time (render + auxiliary pass + denoise + backward + step), the parameter
errors (relative albedo error, |scale - 1|, relative roughness error; their mean is "parameter
error"); ``--evals`` times per run, evenly in time (not timed), the RelMSE of a ``--eval-spp`` render at the
current parameters against the target ("image error"). Also measured, once per scene:

- the wrapped denoiser's forward and forward+backward time against the render's (``costs``);
- the **detachment bias** of the gradient: the derivative the detached auxiliary pass leaves out,
  d loss / d aux . d aux / d theta by central differences of the auxiliary pass (its seed fixed), next
  to the derivative that is kept (``bias``).

    python experiments/inverse_rendering.py [--quick] [--out docs/results/inverse_rendering]

Writes ``inverse_rendering.json``, ``inverse_rendering.md`` (`page`, from the JSON alone) and
``inverse_rendering.png`` (parameter error against wall time, one panel per scene and spp).
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

from common import all_measured, num, write_study

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "results" / "inverse_rendering"
INIT = {"albedo": 0.4, "scale": 0.5, "alpha": 0.5}  # where every run starts
EPS = 0.01  # RelMSE's epsilon (docs/metrics.md)


def build(name: str, size: int):
    """(loaded scene, its parameters, spec) for ``name``; spec maps a role to its parameter key and
    true value."""
    import mitsuba as mi

    import data_gen

    if name == "default":
        scene = data_gen.load_scene(data_gen.default_scene(), width=size, height=size)
        spec = {"albedo": "left.bsdf.reflectance.value", "alpha": "glossy.bsdf.alpha.value",
                "scale": "light.emitter.radiance.value"}
    elif name == "cbox":
        d = mi.cornell_box()
        d["sensor"]["film"].update(width=size, height=size, rfilter={"type": "box"})
        d["small-box"]["bsdf"] = {"type": "roughconductor", "material": "Cu", "distribution": "ggx", "alpha": 0.3}
        scene = mi.load_dict(d)
        spec = {"albedo": "red.reflectance.value", "alpha": "small-box.bsdf.alpha.value",
                "scale": "light.emitter.radiance.value"}
    else:
        raise ValueError(f"unknown scene {name!r}")
    params = mi.traverse(scene)
    truth = {"albedo": np.asarray(params[spec["albedo"]], np.float64).reshape(-1).tolist(),
             "alpha": float(np.asarray(params[spec["alpha"]]).reshape(-1)[0]),
             "radiance": np.asarray(params[spec["scale"]], np.float64).reshape(-1).tolist(), "scale": 1.0}
    return scene, params, spec, truth


class Model:
    """The optimised latent variables and their map onto the scene (albedo clipped to [0.01, 0.99],
    the light as true radiance x exp(log scale), roughness clipped to [0.02, 1])."""

    def __init__(self, params, spec: dict, truth: dict, lr: float):
        import mitsuba as mi

        self.params, self.spec, self.truth = params, spec, truth
        self.radiance = mi.Color3f(truth["radiance"])
        self.opt = mi.ad.Adam(lr=lr)
        self.opt["albedo"] = mi.Color3f(INIT["albedo"])
        self.opt["log_scale"] = mi.Float(np.log(INIT["scale"]))
        self.opt["alpha"] = mi.Float(INIT["alpha"])
        self.apply()

    def apply(self) -> None:
        import drjit as dr

        self.opt["albedo"] = dr.clip(self.opt["albedo"], 0.01, 0.99)
        self.opt["alpha"] = dr.clip(self.opt["alpha"], 0.02, 1.0)
        self.params[self.spec["albedo"]] = self.opt["albedo"]
        self.params[self.spec["alpha"]] = self.opt["alpha"]
        self.params[self.spec["scale"]] = self.radiance * dr.exp(self.opt["log_scale"])
        self.params.update()

    def values(self) -> dict:
        return {"albedo": np.asarray(self.opt["albedo"], np.float64).reshape(-1).tolist(),
                "scale": float(np.exp(np.asarray(self.opt["log_scale"]).reshape(-1)[0])),
                "alpha": float(np.asarray(self.opt["alpha"]).reshape(-1)[0])}

    def errors(self) -> dict:
        v, t = self.values(), self.truth
        e = {"albedo": float(np.linalg.norm(np.subtract(v["albedo"], t["albedo"])) / np.linalg.norm(t["albedo"])),
             "scale": abs(v["scale"] - 1.0), "alpha": abs(v["alpha"] - t["alpha"]) / t["alpha"]}
        e["mean"] = float(np.mean([e["albedo"], e["scale"], e["alpha"]]))
        return e


def relmse_dr(x, target):
    """RelMSE (docs/metrics.md) in Dr.Jit, the target detached."""
    import drjit as dr

    return dr.mean(dr.square(x - target) / (dr.square(target) + EPS), axis=None)


def run(scene_name: str, size: int, loss: str, spp: int, budget: float, max_iters: int, lr: float, target,
        evals: int, eval_spp: int, max_depth: int) -> dict:
    """One optimisation: Adam steps until ``budget`` seconds of wall time (or ``max_iters`` steps);
    the image error evaluated ``evals`` times, evenly in time, and at the end (untimed)."""
    import drjit as dr
    import mitsuba as mi

    import data_gen

    scene, params, spec, truth = build(scene_name, size)
    prb = mi.load_dict({"type": "prb", "max_depth": max_depth})
    model = Model(params, spec, truth, lr)
    den = None if loss == "raw" else data_gen.differentiable(loss)
    tgt = mi.TensorXf(target)
    steps, t_total, next_eval = [], 0.0, 0.0

    def image_error() -> float:
        with dr.suspend_grad():
            img = mi.render(scene, params, spp=eval_spp, seed=10**6, integrator=prb)
        return float(np.mean((np.asarray(img) - target) ** 2 / (target ** 2 + EPS)))

    if den is not None:  # compile the wrapped denoiser's programs and the auxiliary pass's kernels untimed
        img = mi.render(scene, params, spp=spp, seed=0, seed_grad=1, integrator=prb)
        dr.backward(relmse_dr(den(img, den.aux(scene, spp=spp, seed=0, max_depth=max_depth)), tgt))
        for k in ("albedo", "log_scale", "alpha"):
            dr.clear_grad(model.opt[k])
    it = 0
    while True:
        rec = {"step": it, "seconds": t_total, **{f"err_{k}": v for k, v in model.errors().items()}}
        done = t_total >= budget or it >= max_iters
        if t_total >= next_eval or done:
            rec["image_relmse"] = image_error()
            next_eval += budget / evals
        steps.append(rec)
        if done:
            break
        t0 = time.perf_counter()
        img = mi.render(scene, params, spp=spp, seed=2 * it + 1, seed_grad=2 * it + 2, integrator=prb)
        if den is not None:
            img = den(img, den.aux(scene, spp=spp, seed=3 * 10**5 + it, max_depth=max_depth))
        value = relmse_dr(img, tgt)
        dr.backward(value)
        model.opt.step()
        model.apply()
        # Dr.Jit is lazy: the adjoint render runs when its result is first read, so read it on the clock
        steps[-1]["loss"] = float(np.asarray(value).reshape(-1)[0])
        model.values()
        t_total += time.perf_counter() - t0
        it += 1
    final = steps[-1]
    return {"scene": scene_name, "loss": loss, "spp": spp, "iters": it, "lr": lr, "steps": steps,
            "seconds": t_total, "final": model.values(), "truth": truth, "seconds_per_step": t_total / max(it, 1),
            "final_error": {k: final[f"err_{k}"] for k in ("albedo", "scale", "alpha", "mean")},
            "final_image_relmse": final["image_relmse"]}


def costs(scene_name: str, size: int, spp: int, methods: list[str], repeats: int, max_depth: int) -> dict:
    """Medians over ``repeats`` of: the render (primal), the render + raw-loss backward, and per method
    the auxiliary pass, the wrapped denoise forward, and forward + backward into the image."""
    import drjit as dr
    import mitsuba as mi

    import data_gen

    scene, params, _, _ = build(scene_name, size)
    prb = mi.load_dict({"type": "prb", "max_depth": max_depth})

    def med(fn) -> float:
        fn()  # warm-up: Dr.Jit kernels and XLA programs compiled
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
        return statistics.median(ts)

    def render():
        with dr.suspend_grad():
            np.asarray(mi.render(scene, spp=spp, seed=1, integrator=prb))

    key = [k for k in params.keys() if k.endswith("reflectance.value")][0]

    def render_backward():
        dr.enable_grad(params[key])
        params.update()
        img = mi.render(scene, params, spp=spp, seed=1, seed_grad=2, integrator=prb)
        dr.backward(dr.mean(dr.square(img), axis=None))
        np.asarray(dr.grad(params[key]))  # read: Dr.Jit runs the adjoint pass lazily
        dr.disable_grad(params[key])
        params.update()

    out = {"scene": scene_name, "size": size, "spp": spp, "render_s": med(render),
           "render_backward_s": med(render_backward), "methods": {}}
    with dr.suspend_grad():
        image = np.asarray(mi.render(scene, spp=spp, seed=3, integrator=prb))
    for m in methods:
        den = data_gen.differentiable(m)
        aux = den.aux(scene, spp=spp, seed=4, max_depth=max_depth)

        def forward():
            with dr.suspend_grad():
                np.asarray(den(mi.TensorXf(image), aux))

        def backward():
            c = mi.TensorXf(image)
            dr.enable_grad(c)
            dr.backward(dr.mean(den(c, aux), axis=None))
            np.asarray(dr.grad(c))

        out["methods"][m] = {"aux_s": med(lambda: [np.asarray(v) for v in den.aux(scene, spp=spp, seed=4, max_depth=max_depth).values()]),
                             "forward_s": med(forward), "forward_backward_s": med(backward)}
    return out


def detachment_bias(scene_name: str, size: int, spp: int, methods: list[str], target, max_depth: int) -> list[dict]:
    """Per method and parameter, at the start point: the derivative ``dr.backward`` gives (auxiliary
    buffers detached: what the optimisation follows) and the one it leaves out,
    d loss / d aux . d aux / d theta, by central differences of the auxiliary pass (its seed fixed,
    the colour held at the unperturbed render). Albedo: the derivative along albedo x (1 + s)."""
    import drjit as dr
    import mitsuba as mi

    import data_gen

    out = []
    h = 1e-2
    for m in methods:
        scene, params, spec, truth = build(scene_name, size)
        prb = mi.load_dict({"type": "prb", "max_depth": max_depth})
        model = Model(params, spec, truth, lr=0.0)
        den = data_gen.differentiable(m)
        tgt = mi.TensorXf(target)
        img = mi.render(scene, params, spp=spp, seed=11, seed_grad=12, integrator=prb)
        aux0 = den.aux(scene, spp=spp, seed=13, max_depth=max_depth)
        dr.backward(relmse_dr(den(img, aux0), tgt))
        start = {k: np.asarray(model.opt[k], np.float64).reshape(-1) for k in ("albedo", "log_scale", "alpha")}
        kept = {"albedo": float(np.sum(start["albedo"] * np.asarray(dr.grad(model.opt["albedo"])).reshape(-1))),
                "log_scale": float(np.asarray(dr.grad(model.opt["log_scale"])).reshape(-1)[0]),
                "alpha": float(np.asarray(dr.grad(model.opt["alpha"])).reshape(-1)[0])}
        frozen = mi.TensorXf(np.asarray(dr.detach(img)))

        def loss_with_aux(role: str, step: float) -> float:
            moved = {k: v.copy() for k, v in start.items()}
            moved[role] = moved[role] * (1 + step) if role == "albedo" else moved[role] + step
            model.opt["albedo"] = mi.Color3f(moved["albedo"])
            model.opt["log_scale"] = mi.Float(moved["log_scale"])
            model.opt["alpha"] = mi.Float(moved["alpha"])
            model.apply()
            with dr.suspend_grad():
                aux = den.aux(scene, spp=spp, seed=13, max_depth=max_depth)
                return float(np.asarray(relmse_dr(den(frozen, aux), tgt)).reshape(-1)[0])

        left = {role: (loss_with_aux(role, h) - loss_with_aux(role, -h)) / (2 * h) for role in kept}
        out.append({"method": m, "scene": scene_name, "spp": spp, "kept": kept, "left_out": left,
                    "ratio": {k: abs(left[k]) / max(abs(kept[k]), 1e-30) for k in kept}})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--scenes", default="default,cbox")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--spps", default="1,4,16")
    ap.add_argument("--methods", default="gaussian,demc,lbf")
    ap.add_argument("--budget", type=float, default=30.0, help="wall seconds of optimisation per run")
    ap.add_argument("--max-iters", type=int, default=1000)
    ap.add_argument("--lr", type=float, default=0.03)
    ap.add_argument("--ref-spp", type=int, default=64)
    ap.add_argument("--ref-budget", type=float, default=90.0, help="wall seconds of the reference run")
    ap.add_argument("--target-spp", type=int, default=2048)
    ap.add_argument("--evals", type=int, default=6, help="image-error evaluations per run (untimed)")
    ap.add_argument("--eval-spp", type=int, default=256)
    ap.add_argument("--max-depth", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="one scene, 4 spp, 6 steps: a smoke run (not for the page)")
    args = ap.parse_args()
    if args.quick:
        args.scenes, args.spps, args.budget, args.evals, args.repeats = "default", "4", 3.0, 2, 2
        args.target_spp, args.ref_spp, args.eval_spp, args.ref_budget = 64, 16, 16, 3.0
    import drjit as dr
    import mitsuba as mi

    import data_gen
    import jax

    data_gen.setup_mitsuba()
    scenes = args.scenes.split(",")
    spps = [int(s) for s in args.spps.split(",")]
    methods = args.methods.split(",")
    res = {"config": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if k != "out"},
           "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "jax": jax.__version__,
                       "mitsuba": mi.__version__, "drjit": dr.__version__, "variant": mi.variant(),
                       "load_1min_at_start": os.getloadavg()[0]},
           "init": INIT, "runs": [], "costs": [], "bias": []}
    for name in scenes:
        scene, params, _, _ = build(name, args.size)
        prb = mi.load_dict({"type": "prb", "max_depth": args.max_depth})
        with dr.suspend_grad():
            target = np.asarray(mi.render(scene, spp=args.target_spp, seed=99, integrator=prb), np.float32)
        del scene, params
        res["costs"].append(costs(name, args.size, 4, methods, args.repeats, args.max_depth))
        res["bias"] += detachment_bias(name, args.size, 4, [m for m in methods if m != "gaussian"], target, args.max_depth)
        plan = [("raw", args.ref_spp)] + [(loss, s) for s in spps for loss in ["raw"] + methods
                                          if not (loss == "lbf" and s < 2)]
        for loss, s in plan:
            t0 = time.perf_counter()
            ref = (loss, s) == plan[0]
            r = run(name, args.size, loss, s, args.ref_budget if ref else args.budget, args.max_iters, args.lr, target,
                    args.evals, args.eval_spp, args.max_depth)
            r["reference"] = ref
            res["runs"].append(r)
            print(f"{name} {loss}@{s}: param error {r['final_error']['mean']:.4f}, image RelMSE "
                  f"{r['final_image_relmse']:.5f}, {r['seconds']:.1f} s ({time.perf_counter() - t0:.0f} s wall)", flush=True)
    res["machine"]["load_1min_at_end"] = os.getloadavg()[0]
    all_measured(res, "inverse_rendering.json")
    args.out.mkdir(parents=True, exist_ok=True)
    path = write_study(args.out, "inverse_rendering.json", "inverse_rendering.md", res, page)
    plot(res, args.out / "inverse_rendering.png")
    print(path)


def _label(r: dict) -> str:
    return f"{r['loss']}@{r['spp']}" + (" (reference)" if r.get("reference") else "")


def error_at(r: dict, t: float) -> float:
    """The run's parameter error at wall time ``t``: the last step taken by then."""
    err = r["steps"][0]["err_mean"]
    for st in r["steps"]:
        if st["seconds"] > t:
            break
        err = st["err_mean"]
    return err


def page(res: dict) -> str:
    """The result page, from the JSON alone."""
    c, mach = res["config"], res["machine"]
    budget = c["budget"]
    lines = [
        "# Inverse rendering with a denoiser in the loss (issue 39)", "",
        "Written by `experiments/inverse_rendering.py` from `inverse_rendering.json` (regenerate: "
        f"`python experiments/inverse_rendering.py`). {c['size']}x{c['size']} px, `prb` (max depth {c['max_depth']}), "
        f"Adam lr {c['lr']} for {num(budget, 'g')} s of wall time per run (the reference raw@{c['ref_spp']}: "
        f"{num(c['ref_budget'], 'g')} s; at most {c['max_iters']} steps), "
        f"target {c['target_spp']} spp, image error at {c['eval_spp']} spp. Every run starts from albedo "
        f"{res['init']['albedo']}, half the light, roughness {res['init']['alpha']}. Machine: {mach['cpus']} CPUs, "
        f"{mach['variant']}, Mitsuba {mach['mitsuba']}, Dr.Jit {mach['drjit']}, JAX {mach['jax']}; 1-minute load "
        f"{num(mach['load_1min_at_start'], '.2f')} at the start, {num(mach['load_1min_at_end'], '.2f')} at the end.",
        "", "Parameter error = mean of the relative albedo error, |light scale - 1| and the relative roughness "
        "error. Times are wall time of the optimisation (render + detached auxiliary pass + denoise + backward + "
        "step); compilation happens before the clock starts.", ""]
    lines += ["## What the wrapped denoiser costs", "",
              "Medians at 4 spp; `aux` = the detached pass of data_gen's integrator for the buffers the method reads.", "",
              "| scene | render (s) | render + backward (s) | method | aux (s) | denoise forward (s) | forward + backward (s) | (fwd + bwd) / (render + bwd) |",
              "|---|---:|---:|---|---:|---:|---:|---:|"]
    for co in res["costs"]:
        for m, v in co["methods"].items():
            lines.append(f"| {co['scene']} | {num(co['render_s'], '.4f')} | {num(co['render_backward_s'], '.4f')} | {m} | "
                         f"{num(v['aux_s'], '.4f')} | {num(v['forward_s'], '.4f')} | {num(v['forward_backward_s'], '.4f')} | "
                         f"{num(v['forward_backward_s'] / co['render_backward_s'], '.2f')} |")
    lines += ["", "## The detachment bias of the gradient", "",
              "At the start point, 4 spp: the derivative `dr.backward` follows (auxiliary buffers detached) and the "
              "part it leaves out (d loss / d aux . d aux / d theta, central differences of the auxiliary pass with "
              "its seed fixed). Albedo: along albedo x (1 + s).", "",
              "| scene | method | parameter | kept | left out | left out / kept |", "|---|---|---|---:|---:|---:|"]
    for b in res["bias"]:
        for k in ("albedo", "log_scale", "alpha"):
            lines.append(f"| {b['scene']} | {b['method']} | {k} | {num(b['kept'][k], '.4g')} | {num(b['left_out'][k], '.4g')} | "
                         f"{num(b['ratio'][k], '.3f')} |")
    for scene in dict.fromkeys(r["scene"] for r in res["runs"]):
        runs = [r for r in res["runs"] if r["scene"] == scene]
        lines += ["", f"## {scene}: where each loss ends", "",
                  "| loss | steps | s / step | parameter error | albedo | light scale | roughness | image RelMSE |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for r in runs:
            e = r["final_error"]
            lines.append(f"| {_label(r)} | {r['iters']} | {num(r['seconds_per_step'], '.4f')} | {num(e['mean'], '.4f')} | "
                         f"{num(e['albedo'], '.4f')} | {num(e['scale'], '.4f')} | {num(e['alpha'], '.4f')} | "
                         f"{num(r['final_image_relmse'], '.5f')} |")
        lines += ["", f"### {scene}: parameter error at equal wall time", "",
                  "Each loss's parameter error after a quarter, half and all of the budget; **bold**: the lowest of the "
                  "row's spp among raw and denoised losses (the reference excluded).", ""]
        marks = [budget / 4, budget / 2, budget]
        lines += ["| spp | loss | " + " | ".join(f"at {num(t, 'g')} s" for t in marks) + " |",
                  "|---:|---|" + "---:|" * len(marks)]
        for spp in dict.fromkeys(r["spp"] for r in runs if not r.get("reference")):
            group = [r for r in runs if r["spp"] == spp and not r.get("reference")]
            best = [min(error_at(r, t) for r in group) for t in marks]
            for r in group:
                cells = [(f"**{num(error_at(r, t), '.4f')}**" if error_at(r, t) == b else num(error_at(r, t), ".4f"))
                         for t, b in zip(marks, best)]
                lines.append(f"| {spp} | {r['loss']} | " + " | ".join(cells) + " |")
        ref = [r for r in runs if r.get("reference")]
        if ref:
            lines.append(f"| {ref[0]['spp']} | raw (reference) | " + " | ".join(num(error_at(ref[0], t), '.4f') for t in marks) + " |")
    lines += ["", "![parameter error against wall time](inverse_rendering.png)", ""]
    return "\n".join(lines)


def plot(res: dict, path: Path) -> Path:
    """Parameter error against wall time: one panel per scene (rows) and spp (columns)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from jaxdenoise.bench import plot_styles
    from jaxdenoise.fsutil import atomic_path

    scenes = list(dict.fromkeys(r["scene"] for r in res["runs"]))
    spps = list(dict.fromkeys(r["spp"] for r in res["runs"] if not r.get("reference")))
    losses = list(dict.fromkeys(r["loss"] for r in res["runs"]))
    style = plot_styles(losses)
    fig = Figure(figsize=(3.2 * len(spps) + 1.5, 2.8 * len(scenes)), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(scenes), len(spps), squeeze=False)
    for i, scene in enumerate(scenes):
        ref = [r for r in res["runs"] if r["scene"] == scene and r.get("reference")]
        for j, spp in enumerate(spps):
            ax = axes[i][j]
            for r in [r for r in res["runs"] if r["scene"] == scene and r["spp"] == spp and not r.get("reference")]:
                ax.plot([s["seconds"] for s in r["steps"]], [s["err_mean"] for s in r["steps"]], label=r["loss"],
                        color=style[r["loss"]]["color"], lw=1.2)
            for r in ref:
                ax.plot([s["seconds"] for s in r["steps"]], [s["err_mean"] for s in r["steps"]], "k--", lw=1.0,
                        label=f"raw@{r['spp']} (reference)")
            ax.set_yscale("log")
            ax.set_title(f"{scene}, {spp} spp", fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(True, which="both", alpha=0.3)
            if i == len(scenes) - 1:
                ax.set_xlabel("wall time (s)", fontsize=7)
            if j == 0:
                ax.set_ylabel("parameter error", fontsize=7)
    axes[0][-1].legend(fontsize=6, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
    return path


if __name__ == "__main__":
    main()
