"""Builds and executes the notebooks of docs/notebooks (their sources are the cells below):

    python docs/notebooks/build.py            # write + execute all, outputs committed
    python docs/notebooks/build.py quickstart # one of them

Each notebook is executed top to bottom with nbclient in a fresh kernel and saved with its outputs
and, in its metadata, the jaxdenoise version it ran with and a digest of the sources it ran
(``metadata.jaxdenoise.sources_sha256``, `sources_sha256`); tests/test_notebooks.py checks that every
committed notebook has outputs, no error and the current digest (so any change to the library, data_gen
or the shipped weights means rebuilding them), and (slow) executes them again.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

SETUP = """\
import tempfile, time
from pathlib import Path
import numpy as np
import matplotlib.pyplot as plt
import jaxdenoise as jd
import data_gen

WORK = Path(tempfile.mkdtemp(prefix="jaxdenoise_nb_"))  # everything this notebook writes goes here
print("jaxdenoise", jd.__version__, "| Mitsuba variant", data_gen.setup_mitsuba())"""

NOTEBOOKS = {
    "quickstart": [
        ("md", "# Quickstart: render, denoise with every method, compare\n\nRender the built-in scene at 4 "
               "samples per pixel with every buffer any method reads, denoise it with every available method "
               "through `jaxdenoise.denoise`, and look at the results side by side. Then bind a method once "
               "with `jaxdenoise.load` and reuse the jitted function on a second frame."),
        ("code", SETUP),
        ("code", """\
shot = WORK / "default"
rec = data_gen.render_shot(data_gen.default_scene(width=128, height=128), shot, spp=[4], ref_spp=512,
                           methods=jd.method_names(), seed=0, progress=False)
frame, attrs = jd.read_buffers(shot / "spp0004_00.exr")
ref = jd.read_image(shot / "reference.exr")
print("buffers in the frame:", sorted(frame.present()), "| spp", int(frame.spp))"""),
        ("code", """\
from jaxdenoise import metrics
from jaxdenoise.methods import available

names = [m for m, why in available().items() if why is None]
outs, secs = {}, {}
for m in names:
    t = time.perf_counter()
    outs[m] = jd.denoise(frame, method=m)      # shipped weights for the learned methods
    secs[m] = time.perf_counter() - t          # first call: includes compilation
tone = lambda x: np.clip(x, 0, 1) ** (1 / 2.2)
fig, axes = plt.subplots(2, (len(names) + 2) // 2, figsize=(15, 6))
for ax, (title, img) in zip(axes.flat, [("reference (512 spp)", ref)] + list(outs.items())):
    ax.imshow(tone(img)); ax.set_axis_off()
    err = "" if title.startswith("reference") else f"\\nRelMSE {float(metrics.relmse(img, ref)):.3g}"
    ax.set_title(title + err, fontsize=9)
for ax in list(axes.flat)[len(names) + 1:]:
    ax.set_axis_off()
plt.tight_layout()"""),
        ("md", "`jaxdenoise.load` resolves the method and its weights once and returns a jitted function; "
               "the second call on a frame of the same size reuses the compiled program."),
        ("code", """\
infer = jd.load("lbf")
rec2 = data_gen.render_shot(data_gen.default_scene(width=128, height=128), WORK / "second", spp=[4], ref_spp=0,
                            methods=["lbf"], seed=1, progress=False)
frame2, _ = jd.read_buffers(WORK / "second" / "spp0004_00.exr")
for label, f in (("first frame", frame), ("second frame (another noise instance)", frame2)):
    t = time.perf_counter(); out = infer(f); np.asarray(out)
    print(f"{label}: {1e3 * (time.perf_counter() - t):.0f} ms, RelMSE input {float(metrics.relmse(f.color, ref)):.4f} "
          f"-> lbf {float(metrics.relmse(out, ref)):.4f}")"""),
        ("md", "The error differs between noise instances: RelMSE divides by the reference's brightness, so "
               "a few bright samples spread into dark pixels weigh heavily (docs/metrics.md). The bench "
               "(`error_vs_time.ipynb`) averages over frames and sampling rates."),
    ],
    "error_vs_time": [
        ("md", "# Error against run time\n\nRun the bench harness from Python on a small data folder, read "
               "`results.json`, and plot RelMSE against time, with the raw Monte Carlo estimate at several "
               "sample counts as the equal-time reference."),
        ("code", SETUP),
        ("code", """\
data = WORK / "data"
for i in range(2):
    data_gen.render_shot(data_gen.build_scene("mixed", 100 + i, width=64, height=64), data / f"scene_{i}",
                         spp=[4, 16, 64], ref_spp=1024, methods=["gaussian", "bilateral", "lbf", "oidn"], seed=i,
                         progress=False)
from jaxdenoise import bench
report = bench.run(data, ["input", "gaussian", "bilateral", "lbf", "oidn"], WORK / "report", progress=False)
print(bench.one_line(report))"""),
        ("code", """\
import json
res = json.loads((WORK / "report" / "results.json").read_text())
rows = res["summary"]
fig, ax = plt.subplots(figsize=(6.5, 4.5))
for m in dict.fromkeys(r["method"] for r in rows):
    rs = [r for r in rows if r["method"] == m]
    x = [r["render_seconds"] + r["seconds"] for r in rs]
    ax.plot(x, [r["relmse"] for r in rs], "k--o" if m == "input" else "-o", label="raw Monte Carlo" if m == "input" else m)
    for xi, r in zip(x, rs):
        ax.annotate(str(r["spp"]), (xi, r["relmse"]), fontsize=7, xytext=(3, 3), textcoords="offset points")
ax.set(xscale="log", yscale="log", xlabel="render + denoise time (s)", ylabel="RelMSE")
ax.grid(True, which="both", alpha=0.3); ax.legend(fontsize=8)"""),
        ("md", "How to read it: a point left of and below the dashed raw curve is worth its time: the same error "
               "costs less than rendering more samples, or the same time buys less error. A method's points are "
               "its 4, 16 and 64 spp inputs; the horizontal distance between a method and the raw curve at equal "
               "error is the render time it saves. Times are medians of 5 runs after a warm-up, compile apart, on "
               "this machine (docs/metrics.md); the same folder holds `viewer.html` to look at the images."),
    ],
    "train_your_own": [
        ("md", "# Train a learned method on your own renders\n\nRender a tiny training set with data_gen, "
               "train LBF for a few steps from Python with validation on scenes it never trains on, then load "
               "the best weights like shipped ones. (A real run: docs/results/lbf.md; this one is a smoke run "
               "of a few minutes.)"),
        ("code", SETUP),
        ("code", """\
train_dir, val_dir = WORK / "train", WORK / "val"
data_gen.generate_dataset("mixed", 3, train_dir, width=32, spp=(4, 8), instances=1, ref_spp=256, seed=0, progress=False)
data_gen.generate_dataset("mixed", 1, val_dir, width=32, spp=(4, 8), instances=1, ref_spp=256, seed=1000, progress=False)
print(sorted(p.name for p in train_dir.iterdir()))"""),
        ("code", """\
from jaxdenoise.methods import get, lbf
from jaxdenoise.train import TrainConfig, train
method = get("lbf", lbf.Config(radius=5, train_spps=(4, 8), train_crop=24, train_scenes_per_step=2))
run = TrainConfig.for_method(method, steps=60, optimizer="adam", learning_rate=1e-2, val_data=val_dir,
                             validate_every=20, progress=False)
summary = train(method, train_dir, WORK / "run", run)
print(summary["line"].replace(str(WORK), "WORK"))  # WORK: this notebook's temporary folder
for v in summary["validation"]:
    print(f"step {v['step']:3d}: validation RelMSE {v['relmse']:.4f}")"""),
        ("code", """\
infer = jd.load("lbf", WORK / "run" / "best")   # the params with the lowest validation error, and their config
frame, _ = jd.read_buffers(val_dir / "scene_0000" / "spp0004_00.exr")
ref = jd.read_image(val_dir / "scene_0000" / "reference.exr")
from jaxdenoise import metrics
print("input RelMSE", float(metrics.relmse(frame.color, ref)), "| denoised", float(metrics.relmse(infer(frame), ref)))"""),
    ],
    "stability_and_leave_out": [
        ("md", "# Stiff inputs, clear errors, and leaving out what a scene does not need\n\nEvery method is "
               "fed fireflies of 1e6, an all-black frame and a frame with NaN: the output stays finite, or the "
               "call fails with an error that says what is wrong. Then: which buffers each method needs, and "
               "the render time saved by rendering only those."),
        ("code", SETUP),
        ("code", """\
from jaxdenoise.methods import available, get
shot = WORK / "s"
data_gen.render_shot(data_gen.default_scene(width=64, height=64), shot, spp=[4], ref_spp=0,
                     methods=jd.method_names(), seed=0, progress=False)
frame, _ = jd.read_buffers(shot / "spp0004_00.exr")
fire = frame.color.copy(); fire[10, 10] = 1e6
cases = {"firefly 1e6": frame.replace(color=fire), "all black": frame.replace(color=0 * frame.color),
         "NaN row": frame.replace(color=np.where(np.arange(64)[:, None, None] == 5, np.nan, frame.color))}
for m, why in available().items():
    if why:
        continue
    line = []
    for name, b in cases.items():
        try:
            out = jd.denoise(b, method=m)
            line.append(f"{name}: finite={bool(np.isfinite(out).all())}, max {float(np.nanmax(out)):.3g}")
        except Exception as e:
            line.append(f"{name}: {type(e).__name__}: {str(e)[:70]}")
    print(f"{m:11s} " + " | ".join(line))"""),
        ("code", """\
for m in jd.method_names():
    print(f"{m:11s} needs {sorted(get(m).needs())}")"""),
        ("code", """\
import json
timings = {}
for label, methods in (("gaussian only", ["gaussian"]), ("lbf", ["lbf"]), ("every buffer", None)):
    d = WORK / label.replace(" ", "_")
    rec = data_gen.render_shot(data_gen.default_scene(width=128, height=128), d, spp=[16], ref_spp=0,
                               methods=methods, seed=0, progress=False)
    f = rec["files"]["spp0016_00.exr"]
    timings[label] = f["seconds"]
    print(f"{label:13s}: {len(f['fields'])} buffers, {f['seconds']:.3f} s (Dr.Jit compilation excluded: "
          f"{f['compile_seconds']:.3f} s apart)")
print(f"leaving out what gaussian does not need saves {100 * (1 - timings['gaussian only'] / timings['every buffer']):.0f} % "
      "of the render time")"""),
    ],
    "differentiable": [
        ("md", "# Denoisers inside Mitsuba's render loop\n\nRender a Mitsuba scene straight into "
               "`jaxdenoise.Buffers` (no EXR on the way) and denoise it; then put a denoiser inside an "
               "inverse-rendering loop: `data_gen.differentiable` wraps a JAX method with `drjit.wrap`, so "
               "`dr.backward` reaches the scene parameters through it (docs/drjit_bridge.md). The colour comes "
               "from Mitsuba's differentiable `prb` integrator; the albedo, normal and position buffers DEMC "
               "reads come from a detached pass of data_gen's integrator, a bias the page measures."),
        ("code", SETUP),
        ("code", """\
import drjit as dr
import mitsuba as mi

scene = data_gen.load_scene(data_gen.default_scene(), width=64, height=64)
frame = data_gen.render_frame(scene, spp=4, methods=["demc"], seed=0)   # Buffers in memory
print("buffers:", sorted(frame.present()))
clean = np.asarray(mi.render(scene, spp=1024, seed=1))
out = jd.denoise(frame, "demc")
from jaxdenoise import metrics
tone = lambda x: np.clip(x, 0, 1) ** (1 / 2.2)
fig, axes = plt.subplots(1, 3, figsize=(9, 3))
for ax, (t, img) in zip(axes, [("4 spp", frame.color), ("demc", out), ("1024 spp", clean)]):
    ax.imshow(tone(img)); ax.set_axis_off()
    ax.set_title(t if t == "1024 spp" else f"{t}, RelMSE {float(metrics.relmse(img, clean)):.3g}", fontsize=9)"""),
        ("md", "An inverse-rendering run: recover the left wall's albedo and the light's intensity from a "
               "1024-spp target, starting from grey and half the light, with the loss on the 4-spp render "
               "denoised by DEMC. Its auxiliary buffers are re-rendered (detached) every step."),
        ("code", """\
params = mi.traverse(scene)
key_albedo, key_light = "left.bsdf.reflectance.value", "light.emitter.radiance.value"
truth = {"albedo": np.asarray(params[key_albedo]).ravel().copy(), "light": mi.Color3f(params[key_light])}
prb = mi.load_dict({"type": "prb", "max_depth": 4})
den = data_gen.differentiable("demc")
target = mi.TensorXf(clean)
opt = mi.ad.Adam(lr=0.03)
opt["albedo"], opt["log_scale"] = mi.Color3f(0.4), mi.Float(np.log(0.5))

def update():
    opt["albedo"] = dr.clip(opt["albedo"], 0.01, 0.99)
    params[key_albedo] = opt["albedo"]
    params[key_light] = truth["light"] * dr.exp(opt["log_scale"])
    params.update()

update()
history, t0 = [], time.perf_counter()
for it in range(60):
    img = mi.render(scene, params, spp=4, seed=2 * it + 1, seed_grad=2 * it + 2, integrator=prb)
    aux = den.aux(scene, spp=4, seed=10_000 + it)          # detached albedo, normal, position, ...
    loss = dr.mean(dr.square(den(img, aux) - target) / (dr.square(target) + 0.01), axis=None)
    dr.backward(loss)
    opt.step(); update()
    history.append((float(np.asarray(loss).ravel()[0]), np.asarray(opt["albedo"]).ravel().copy(),
                    float(np.exp(np.asarray(opt["log_scale"]).ravel()[0]))))
print(f"{len(history)} steps in {time.perf_counter() - t0:.1f} s (first step compiles)")
print("albedo", np.round(history[-1][1], 3), "true", np.round(truth["albedo"], 3),
      "| light scale", round(history[-1][2], 3), "true 1")"""),
        ("code", """\
fig, axes = plt.subplots(1, 2, figsize=(9, 3))
axes[0].semilogy([h[0] for h in history]); axes[0].set_title("loss (RelMSE, denoised)", fontsize=9)
for c, name in enumerate("RGB"):
    axes[1].plot([h[1][c] for h in history], color=name.lower(), label=f"albedo {name}")
    axes[1].axhline(truth["albedo"][c], color=name.lower(), ls=":")
axes[1].plot([h[2] for h in history], "k", label="light scale"); axes[1].axhline(1, color="k", ls=":")
axes[1].legend(fontsize=7); axes[1].set_title("parameters (dotted: truth)", fontsize=9)
plt.tight_layout()"""),
        ("md", "docs/results/inverse_rendering/inverse_rendering.md measures this at 1, 4 and 16 spp on two "
               "scenes, against the raw-render loss at equal wall time, with the detachment bias of the gradient."),
    ],
}


def sources_sha256() -> str:
    """A digest of what the notebooks run: every Python source of jaxdenoise and data_gen, and the
    shipped weights and scenes (paths and bytes, in path order). A notebook executed before any of
    them changed is stale (tests/test_notebooks.py)."""
    import hashlib

    root = HERE.parents[1]
    files = [p for pkg in ("jaxdenoise", "data_gen") for p in (root / pkg).rglob("*")
             if p.is_file() and p.suffix in (".py", ".npz", ".json", ".xml", ".exr")]
    h = hashlib.sha256()
    for p in sorted(files, key=lambda q: q.relative_to(root).as_posix()):
        h.update(p.relative_to(root).as_posix().encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


def build(name: str) -> Path:
    import nbformat
    from nbclient import NotebookClient

    import jaxdenoise

    nb = nbformat.v4.new_notebook()
    nb.cells = [nbformat.v4.new_markdown_cell(src) if kind == "md" else nbformat.v4.new_code_cell(src)
                for kind, src in NOTEBOOKS[name]]
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    t0 = time.perf_counter()
    NotebookClient(nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(HERE)}}).execute()
    nb.metadata["jaxdenoise"] = {"version": jaxdenoise.__version__, "sources_sha256": sources_sha256(),
                                 "executed_seconds": round(time.perf_counter() - t0, 1)}
    path = HERE / f"{name}.ipynb"
    tmp = path.with_name(f".{path.name}.tmp")
    nbformat.write(nb, tmp)
    tmp.replace(path)
    return path


if __name__ == "__main__":
    for n in (sys.argv[1:] or list(NOTEBOOKS)):
        t = time.perf_counter()
        print(f"{build(n)} ({time.perf_counter() - t:.0f} s)", flush=True)
