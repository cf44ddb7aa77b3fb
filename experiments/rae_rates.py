"""RAE at every sampling rate (issue 34): the input transforms measured at an equal budget, then the
chosen one trained on; every run a fine-tune of the paper-recipe weights on the scene library's
fly-throughs and the procedural families at 1/4/16 spp.

    python experiments/rae_rates.py arms --steps 400 --out runs/rae_rates
    python experiments/rae_rates.py continue --arm rate --steps 2000 --out runs/rae_rates

``arms`` fine-tunes three readings of the input from ``--init`` (default the paper-recipe weights,
``jaxdenoise/weights/rae-paper``), each with ``exposure = "frame"`` (the colour scaled to a fixed level
by the frame's exposure statistic, the output scaled back) and the same crops (one seed):

- ``power``: the paper's input, the demodulated colour raised to 0.2 (Sec. 4.4);
- ``rate``: the same plus the sampling rate as an input channel (log2 spp / 4), its first-layer
  weights started at 0 so the network starts as ``power``'s;
- ``linear``: the demodulated colour itself, the 0.2 power kept in the loss and the output only.

They train on ``--data`` (default ``runs/rae_rates_data``: symlinks to the library's training
fly-throughs and the procedural ones, jaxdenoise/weights/rae/README.md) and validate on the
library's validation fly-throughs (``--val-data``, every rate, state carried) every
``--validate-every`` steps, keeping ``best/`` by the geometric mean of the validation RelMSE.
``continue`` trains one arm further (the same run folder, resumed: ``--steps`` is the new total).
``level`` fine-tunes the shipped weights (``--init jaxdenoise/weights/rae``) with the level term
(`jaxdenoise.methods.rae.Config.level_weight`, ``--level-weight``) at a constant Adam rate (``--lr``)
on crops of ``--seed``, in ``OUT/level{W}_lr{LR}_s{SEED}``:

    python experiments/rae_rates.py level --level-weight 1 --lr 1e-4 --seed 3 --steps 300 \
        --init jaxdenoise/weights/rae --out runs/rae_level

``clamp`` chooses the outlier clamp (`jaxdenoise.methods.rae.Config.outlier_clamp`) of the weights in
``--init`` on the validation fly-throughs only, with no training: for each factor in ``--factors`` the
validation RelMSE (state carried, as training selects) and the colour level of the single frames on
surface pixels (`demc_levels.measure`); the rule: the factor with the lowest geometric-mean RelMSE among
those whose level (every channel and rate) moves by less than ``--level-tolerance`` from the unclamped
one. Written to ``OUT/outlier_clamp.json``:

    python experiments/rae_rates.py clamp --init jaxdenoise/weights/rae --out docs/results/rae_rates

``match`` chooses the level match at inference (`jaxdenoise.methods.rae.Config.match_level`,
``match_max_gain``; docs/methods/rae.md "Colour level at inference") of the weights in ``--init`` the
same way, no training: ``--sigmas`` x ``--gains`` x the cut (a fixed factor from ``--spikes``, labels
``kN``, or one sample's factor from ``--rate-spikes`` scaled by the frame's rate, labels ``rN``:
``match_spike_by_rate``; none by default) and off, each scored by the validation RelMSE (state
carried) and the single frames' surface level. The rule (the issue's 3 %
is out of reach at 1 spp, where a gain that large spreads outliers): among the settings whose
geometric-mean RelMSE is at most ``--relmse-tolerance`` times off's and whose RelMSE at every rate is at
most ``--rate-tolerance`` times off's there, the one whose largest distance of a level from 1 (every
channel and rate) is smallest; off unless that beats off's. (The per-rate bound was added after a first
run without it chose sigma 8, gain 1.3, whose 16-spp validation RelMSE was 54 % above off's: one frame's
surviving outlier brightened 1.3x, docs/methods/rae.md.) Written to ``OUT/level_match.json``:

    python experiments/rae_rates.py match --init jaxdenoise/weights/rae --out docs/results/rae_rates

``exact`` chooses whether and how `rae` keeps exact pixels (`jaxdenoise.methods.rae.Config.keep_exact`,
``exact_window``; docs/methods/rae.md "Exact pixels") for the weights and settings in ``--init``, no
training: off, the variance rule alone (window 0) and each window of ``--windows``, scored on the
validation fly-throughs (``--val-data``, state carried) and the validation single frames of
``--exact-data`` together: the geometric mean of every frame's RelMSE. The rule: the setting with the
lowest geometric mean; off unless that beats off's. Each setting's kept pixels are counted per folder,
and those that are not exact (a channel more than 5 % from the reference's). Written to
``OUT/exact_pixels.json``:

    python experiments/rae_rates.py exact --init jaxdenoise/weights/rae --out docs/results/rae_rates

``taa`` chooses temporal anti-aliasing (`jaxdenoise.methods.rae.Config.taa_alpha`, ``taa_window``,
``taa_tolerance``; docs/methods/rae.md "Temporal anti-aliasing") for the weights and settings in
``--init``, no training: off and every combination of ``--alphas`` x ``--taa-windows`` x
``--tolerances``, each run over the validation fly-throughs of ``--val-data`` and ``--taa-data``
(state carried, the sequence driver) and scored per sequence and rate by the mean RelMSE of its
frames and its temporal error (`jaxdenoise.metrics.temporal_error`), and per rate by the colour level
of its frames after the first (`demc_levels.frame_levels` over every lit pixel: per channel, the
median over those frames). The rule: among the settings whose mean RelMSE at every rate is at most
off's and whose level (every rate and channel) is at most ``--level-slack`` further from 1 than off's,
the lowest geometric mean over sequences and rates of sqrt(RelMSE x temporal error); off unless that
beats off's. Written to ``OUT/taa.json``:

    python experiments/rae_rates.py taa --init jaxdenoise/weights/rae --out docs/results/rae_rates

``accumulate`` chooses the input accumulation (`jaxdenoise.methods.rae.Config.accumulate_samples`,
``accumulate_tolerance``, ``accumulate_clamp``; docs/methods/rae.md "Input accumulation") for the weights
and settings in ``--init``, no training: off and every combination of ``--samples`` x ``--tolerances`` x
``--clamps``, scored on the same fly-throughs and by the same rule as ``taa``, with the level slack
``--level-slack`` (the documented choice used 0.005, fixed before it ran). Written to
``OUT/accumulate.json``:

    python experiments/rae_rates.py accumulate --init jaxdenoise/weights/rae --tolerances 0.02,0.05 \
        --level-slack 0.005 --out docs/results/rae_rates/accumulate

``background`` chooses whether `rae` keeps its input on background pixels (a zero normal: the environment
seen directly; `jaxdenoise.methods.rae.Config.keep_background`, docs/methods/rae.md "Background") for the
weights and settings in ``--init``, no training: off and on, scored on the same fly-throughs and by the
same rule as ``taa`` (the documented choice used ``--level-slack 0.005``, fixed before it ran). Written to
``OUT/background.json``:

    python experiments/rae_rates.py background --init runs/rae_0920 --level-slack 0.005 \
        --out docs/results/rae_rates/background

``match-frames`` chooses the level match over time (`jaxdenoise.methods.rae.Config.match_frames`,
``match_tolerance``; docs/methods/rae.md "The level match over time") for the weights and settings in
``--init``, no training: off (each frame's own gain) and every combination of ``--match-frames`` x
``--tolerances``, scored on the same fly-throughs and by the same rule as ``taa`` (the documented choice
used ``--level-slack 0.005``, fixed before it ran). Written to ``OUT/match-frames.json``:

    python experiments/rae_rates.py match-frames --init jaxdenoise/weights/rae --match-frames 2,4,8,16 \
        --level-slack 0.005 --out docs/results/rae_rates/match_frames

``single-sample`` chooses whether and where the outlier clamp drops its floor on pixels that rest on about one
sample (`jaxdenoise.methods.rae.Config.outlier_rel_sd`; docs/methods/rae.md "Single-sample spikes") for the
weights and settings in ``--init``, no training: off and each relative standard error of ``--rel-sds``, scored
on the validation fly-throughs (``--val-data`` and ``--taa-data``, state carried, as ``taa``) and on the
validation single frames of ``--exact-data`` at 1 / 4 / 16 / 64 spp (`demc_levels.measure`, surface pixels).
The rule, fixed before it first ran: among the settings whose fly-through RelMSE at every rate and whose
single frames' geometric-mean RelMSE are at most ``--relmse-tolerance`` times off's, and whose levels (the
fly-throughs' per rate, the single frames' per rate pooled over folders; every channel) are at most
``--level-slack`` further from 1 than off's, the one with the fewest halo pixels (the single frames' surface
halo pixels plus the fly-throughs'), ties broken by the fly-through score; off unless that has fewer than
off's. Written to ``OUT/single_sample.json``:

    python experiments/rae_rates.py single-sample --init jaxdenoise/weights/rae --level-slack 0.005 \
        --out docs/results/rae_rates/single_sample

Every training run's record goes to ``OUT/summary.json``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for _p in (ROOT, ROOT / "experiments"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

from jaxdenoise import checkpoint  # noqa: E402
from jaxdenoise.fsutil import write_json  # noqa: E402
from jaxdenoise.methods import get  # noqa: E402
from jaxdenoise.train import SELECT, TrainConfig, load_data, train  # noqa: E402

SPPS = (1, 4, 16)
ARMS = {"power": {"input_transform": "power", "rate_input": False},
        "rate": {"input_transform": "power", "rate_input": True},
        "linear": {"input_transform": "linear", "rate_input": False}}


def _method(arm: str, **config):
    return get("rae", train_spps=SPPS, exposure="frame", recipe="", **ARMS[arm], **config)


def start_weights(init: Path, method, out: Path) -> Path:
    """``init``'s weights as a start for ``method``: with the rate channel, the first convolution gets
    one more input row, zero (the network then starts as it was); written to ``out``."""
    params, meta = checkpoint.load(init)
    if method.config.rate_input and not meta.get("config", {}).get("rate_input"):
        w = np.asarray(params["enc"]["0"]["w"])
        params["enc"]["0"]["w"] = np.concatenate([w, np.zeros(w.shape[:2] + (1,) + w.shape[3:], w.dtype)], 2)
    checkpoint.save(out, params, method.config, {"method": "rae", "started_from": str(init)})
    return out


def _train_arm(arm: str, data, out: Path, args, steps: int, name: str | None = None, **config) -> dict:
    method = _method(arm, **config)
    init = start_weights(Path(args.init), method, out / "start")
    fields = {"schedule": "constant", "seed": args.seed} if config else {}
    if args.ema:  # `level` runs only (main refuses it elsewhere)
        fields["ema"] = args.ema
    run = TrainConfig.for_method(method, steps=steps, resume=True, val_data=args.val_data, init_from=str(init),
                                 validate_every=args.validate_every, select=args.select, progress=False,
                                 learning_rate=args.lr, time_limit=args.seconds, **fields)
    t = time.perf_counter()
    s = train(method, data, out / (name or arm), run)
    rec = {"steps": s["steps_done"], "steps_this_run": s["steps_this_run"], "seconds": time.perf_counter() - t,
           "final_loss": s["final_loss"], "best_step": s["best"]["step"],
           "best_geomean": s["best"]["relmse_geomean"], "best_per_spp": s["best"].get("per_spp"),
           "best_halo": s["best"].get("halo"), "select": args.select,
           "config": ARMS[arm] | {"exposure": "frame", "train_spps": list(SPPS)} | config | fields,
           "validation": [{k: v.get(k) for k in ("step", "relmse", "relmse_geomean", "per_spp", "ssim", "halo",
                                                 "halo_per_spp")}
                          for v in s["validation"]]}
    print(name or arm, {k: rec[k] for k in ("steps", "seconds", "best_step", "best_geomean")}, flush=True)
    return rec


def choose_clamp(args) -> dict:
    """The ``clamp`` subcommand (module docstring): for each factor the validation RelMSE (state carried,
    as training selects) and the single frames' colour level on surface pixels (`demc_levels.measure`)
    of the weights in ``--init``, no training; then the rule."""
    import tempfile

    from demc_levels import measure
    from jaxdenoise.api import resolve
    from jaxdenoise.train import load_validation, validate

    factors = [float(f) for f in args.factors.split(",")]
    base, params = resolve("rae", args.init)
    frames = load_validation(base, args.val_data)
    res = {"init": args.init, "val_data": args.val_data, "level_tolerance": args.level_tolerance, "factors": {}}
    with tempfile.TemporaryDirectory() as tmp:
        folders = {}
        for f in factors:
            m = base.with_config(outlier_clamp=f)
            v = validate(m, params, frames)
            folders[f] = checkpoint.save(Path(tmp) / f"k{f:g}", params, m.config, {"method": "rae"})
            res["factors"][f"{f:g}"] = {k: v[k] for k in ("relmse", "relmse_geomean", "per_spp", "ssim")}
            print(f"{f:g}", {k: v[k] for k in ("relmse_geomean", "per_spp")}, flush=True)
        spps = sorted({int(fr["spp"]) for fr in frames})
        lv = measure([f"k{f:g}={folders[f]}" for f in factors], [args.val_data], spps)
    for f in factors:
        levels = lv["methods"][f"k{f:g}"]["levels"][args.val_data]
        res["factors"][f"{f:g}"]["level"] = {s: np.median(v, 0).tolist() for s, v in levels.items()}
    ref = res["factors"][f"{factors[0]:g}"]["level"]
    ok = [f for f in factors if all(abs(a - b) < args.level_tolerance for s in ref
                                     for a, b in zip(res["factors"][f"{f:g}"]["level"][s], ref[s]))]
    res["chosen"] = f"{min(ok, key=lambda f: res['factors'][f'{f:g}']['relmse_geomean']):g}"
    res["command"] = " ".join(["python", "experiments/rae_rates.py", *sys.argv[1:]])
    return res


def choose_match(args) -> dict:
    """The ``match`` subcommand (module docstring): validation RelMSE and surface level of each level-
    match setting of the weights in ``--init``, then the rule."""
    import tempfile

    from demc_levels import measure
    from jaxdenoise.api import resolve
    from jaxdenoise.train import load_validation, validate

    base, params = resolve("rae", args.init)
    val = [d for d in args.val_data.split(",") if d.strip()]
    frames = [fr for d in val for fr in load_validation(base, d)]
    settings = {"off": {"match_level": 0.0}}
    cuts = [c == "1" for c in args.output_cuts.split(",")]
    for sigma in (float(s) for s in args.sigmas.split(",")):
        for gain in (float(g) for g in args.gains.split(",")):
            spikes = [(float(k), False) for k in args.spikes.split(",")]
            spikes += [(float(k), True) for k in args.rate_spikes.split(",") if k.strip()]
            for (spike, by_rate), cut in ((sp, c) for sp in spikes for c in cuts):
                settings[f"s{sigma:g} g{gain:g} {'r' if by_rate else 'k'}{spike:g}{' o' if cut else ''}"] = {
                    "match_level": sigma, "match_max_gain": gain, "match_spike": spike, "match_spike_by_rate": by_rate,
                    "match_output_cut": cut}
    res = {"init": args.init, "val_data": args.val_data, "relmse_tolerance": args.relmse_tolerance,
           "rate_tolerance": args.rate_tolerance, "settings": {}}
    with tempfile.TemporaryDirectory() as tmp:
        folders = {}
        for label, over in settings.items():
            m = base.with_config(**over)
            v = validate(m, params, frames)
            folders[label] = checkpoint.save(Path(tmp) / label.replace(" ", "_"), params, m.config, {"method": "rae"})
            res["settings"][label] = {"config": over} | {k: v[k] for k in ("relmse", "relmse_geomean", "per_spp",
                                                                             "ssim")}
            print(label, {k: v[k] for k in ("relmse_geomean", "per_spp")}, flush=True)
        spps = sorted({int(fr["spp"]) for fr in frames})
        lv = measure([f"{k.replace(' ', '_')}={f}" for k, f in folders.items()], val, spps)
    for label, r in res["settings"].items():
        levels = lv["methods"][label.replace(" ", "_")]["levels"]
        r["level"] = {s: np.median([x for d in val for x in levels[d][s]], 0).tolist() for s in levels[val[0]]}
        r["level_distance"] = max(abs(x - 1) for lvl in r["level"].values() for x in lvl)
    off = res["settings"]["off"]
    ok = [k for k, r in res["settings"].items()
          if r["relmse_geomean"] <= args.relmse_tolerance * off["relmse_geomean"]
          and all(r["per_spp"][s] <= args.rate_tolerance * off["per_spp"][s] for s in off["per_spp"])]
    best = min(ok, key=lambda k: res["settings"][k]["level_distance"])
    res["chosen"] = best if res["settings"][best]["level_distance"] < off["level_distance"] else "off"
    res["command"] = " ".join(["python", "experiments/rae_rates.py", *sys.argv[1:]])
    return res


def choose_exact(args) -> dict:
    """The ``exact`` subcommand (module docstring): the validation RelMSE of each exact-pixel setting of
    the weights in ``--init`` and the pixels it keeps, then the rule."""
    from jaxdenoise.api import resolve
    from jaxdenoise.filters import exact_mask
    from jaxdenoise.train import load_validation, validate

    base, params = resolve("rae", args.init)
    reader = base.with_config(keep_exact=True)  # reads color_var where a frame has it
    folders = [args.val_data] + [d for d in args.exact_data.split(",") if d.strip()]
    frames = {d: load_validation(reader, d) for d in folders}
    settings = {"off": {"keep_exact": False, "exact_window": 0}, "variance": {"keep_exact": True, "exact_window": 0}}
    settings |= {f"w{w}": {"keep_exact": True, "exact_window": int(w)} for w in args.windows.split(",")}
    res = {"init": args.init, "folders": folders, "settings": {}}
    counts = {d: sum(len(f["frames"]) if "frames" in f else 1 for f in fr) for d, fr in frames.items()}
    for label, over in settings.items():
        m = base.with_config(**over)
        per = {d: validate(m, params, fr) for d, fr in frames.items()}
        # the geometric mean over every frame, from each folder's (weighted by its frames)
        every = float(np.exp(sum(counts[d] * np.log(v["relmse_geomean"]) for d, v in per.items())
                             / sum(counts.values())))
        kept = {d: {"kept": 0, "not_exact": 0} for d in frames}
        for d, fr in frames.items() if over["keep_exact"] else ():
            for f in fr:
                pairs = zip(f["frames"], f["references"]) if "frames" in f else [(f["buffers"], f["reference"])]
                for b, ref in pairs:
                    mask = np.asarray(exact_mask(b.color, b.color_var, b.spp, window=over["exact_window"]))[..., 0]
                    c, r = np.asarray(b.color, np.float64)[mask], np.asarray(ref, np.float64)[mask]
                    kept[d]["kept"] += int(mask.sum())
                    kept[d]["not_exact"] += int(np.sum(np.any(np.abs(c - r) > 0.05 * np.abs(r) + 1e-6, axis=-1)))
        res["settings"][label] = {"config": over, "relmse_geomean": every,
                                  "folders": {d: {x: v[x] for x in ("relmse", "relmse_geomean", "per_spp")} | kept[d]
                                              for d, v in per.items()}}
        print(label, every, {d: (v["relmse_geomean"], kept[d]) for d, v in per.items()}, flush=True)
    best = min(res["settings"], key=lambda k: res["settings"][k]["relmse_geomean"])
    beats = res["settings"][best]["relmse_geomean"] < res["settings"]["off"]["relmse_geomean"]
    res["chosen"] = best if beats else "off"
    res["command"] = " ".join(["python", "experiments/rae_rates.py", *sys.argv[1:]])
    return res


def _validation_sequences(args, base):
    """The validation fly-throughs of ``--val-data`` and ``--taa-data`` (frames read with the positions,
    normals and cameras that reprojection needs): ``(folders, [(folder, sequence), ...])``."""
    from jaxdenoise.train import load_validation

    reader = base.with_config(taa_alpha=1.0)
    folders = [args.val_data] + [d for d in args.taa_data.split(",") if d.strip()]
    seqs = [(d, f) for d in folders for f in load_validation(reader, d) if "frames" in f]
    if not seqs:
        raise SystemExit(f"{args.what}: no validation fly-through in {folders}")
    return folders, seqs


def _temporal_choice(args, base, params, seqs, settings: dict[str, dict], res: dict) -> dict:
    """Score each of ``settings`` (label -> config overrides, ``"off"`` first) over ``seqs`` (the sequence
    driver, state carried) by TAA's rule (module docstring, ``taa``) and record them and the choice in
    ``res``."""
    from demc_levels import frame_levels
    from jaxdenoise import metrics
    from jaxdenoise.sequence import run_all

    res["settings"] = {}
    for label, over in settings.items():
        m = base.with_config(**over)
        rows = []
        for d, f in seqs:
            outs, refs = run_all(m, params, f["frames"]), np.stack(f["references"])
            rows.append({"folder": d, "spp": int(f["spp"]),
                         "relmse": float(np.mean([metrics.relmse(o, r) for o, r in zip(outs, refs)])),
                         "temporal": float(metrics.temporal_error(outs, refs)),
                         "levels": [frame_levels(o, r) for o, r in zip(outs[1:], refs[1:])],
                         "halo": metrics.halo_pixels(outs, refs)})
        per_spp = {str(s): {"relmse": float(np.mean([r["relmse"] for r in rows if r["spp"] == s])),
                            "temporal": float(np.mean([r["temporal"] for r in rows if r["spp"] == s])),
                            "level": np.median([lv for r in rows if r["spp"] == s for lv in r["levels"]], 0).tolist()}
                   for s in sorted({r["spp"] for r in rows})}
        score = float(np.exp(np.mean([0.5 * (np.log(r["relmse"]) + np.log(r["temporal"])) for r in rows])))
        res["settings"][label] = {"config": over, "score": score, "per_spp": per_spp, "rows": rows}
        print(label, f"{score:.5f}", per_spp, flush=True)
    off = res["settings"]["off"]

    def level_ok(r: dict) -> bool:
        return all(abs(a - 1) <= abs(b - 1) + args.level_slack
                   for s in off["per_spp"] for a, b in zip(r["per_spp"][s]["level"], off["per_spp"][s]["level"]))
    ok = [k for k, r in res["settings"].items()
          if all(r["per_spp"][s]["relmse"] <= off["per_spp"][s]["relmse"] for s in off["per_spp"]) and level_ok(r)]
    best = min(ok, key=lambda k: res["settings"][k]["score"])
    res["chosen"] = best if res["settings"][best]["score"] < off["score"] else "off"
    res["command"] = " ".join(["python", "experiments/rae_rates.py", *sys.argv[1:]])
    return res


def choose_temporal(args) -> dict:
    """The ``taa``, ``accumulate``, ``background`` and ``match-frames`` subcommands (module docstring): RelMSE,
    temporal error
    and level of each setting of the weights in ``--init`` on the validation fly-throughs, then TAA's rule."""
    from jaxdenoise.api import resolve

    base, params = resolve("rae", args.init)
    folders, seqs = _validation_sequences(args, base)
    tolerances = [float(x) for x in args.tolerances.split(",")]
    if args.what == "taa":
        settings = {"off": {"taa_alpha": 0.0}}
        settings |= {f"a{a:g} w{w} t{t:g}": {"taa_alpha": a, "taa_window": w, "taa_tolerance": t}
                     for a in (float(x) for x in args.alphas.split(","))
                     for w in (int(x) for x in args.taa_windows.split(",")) for t in tolerances}
    elif args.what == "match-frames":
        settings = {"off": {"match_frames": 0.0}}
        settings |= {f"f{n:g} t{t:g}": {"match_frames": n, "match_tolerance": t}
                     for n in (float(x) for x in args.match_frames.split(",")) for t in tolerances}
    elif args.what == "background":
        settings = {"off": {"keep_background": False}, "on": {"keep_background": True}}
    else:
        settings = {"off": {"accumulate_samples": 0.0}}
        settings |= {f"s{n:g} t{t:g} c{c:g}": {"accumulate_samples": n, "accumulate_tolerance": t,
                                                "accumulate_clamp": c}
                     for n in (float(x) for x in args.samples.split(","))
                     for t in tolerances for c in (float(x) for x in args.clamps.split(","))}
    res = {"init": args.init, "folders": folders, "sequences": len(seqs), "level_slack": args.level_slack}
    return _temporal_choice(args, base, params, seqs, settings, res)


def choose_single_sample(args) -> dict:
    """The ``single-sample`` subcommand (module docstring): the fly-throughs scored as ``taa`` does, the single
    frames by `demc_levels.measure`, then the rule."""
    import tempfile

    from demc_levels import measure
    from jaxdenoise.api import resolve

    base, params = resolve("rae", args.init)
    folders, seqs = _validation_sequences(args, base)
    settings = {"off": {"outlier_rel_sd": 0.0}}
    settings |= {f"r{x:g}": {"outlier_rel_sd": x} for x in (float(v) for v in args.rel_sds.split(","))}
    res = _temporal_choice(args, base, params, seqs, settings, {"init": args.init, "folders": folders,
                                                                  "sequences": len(seqs),
                                                                  "level_slack": args.level_slack,
                                                                  "relmse_tolerance": args.relmse_tolerance})
    del res["chosen"]  # TAA's rule; this subcommand's is below
    single = [d for d in args.exact_data.split(",") if d.strip()]
    with tempfile.TemporaryDirectory() as tmp:
        saved = {k: checkpoint.save(Path(tmp) / k, params, base.with_config(**over).config, {"method": "rae"})
                 for k, over in settings.items()}
        lv = measure([f"{k}={f}" for k, f in saved.items()], single, [1, 4, 16, 64])
    res["single_folders"] = single
    for label, r in res["settings"].items():
        m = lv["methods"][label]
        rates = sorted({s for d in single for s in m["levels"][d]}, key=int)
        r["single"] = {
            "relmse_geomean": float(np.exp(np.mean([np.log(x[0]) for d in single for s in rates
                                                    for x in m["scores"][d].get(s, [])]))),
            "level": {s: np.median([x for d in single for x in m["levels"][d].get(s, [])], 0).tolist() for s in rates},
            "halo": {s: int(sum(sum(m["halo_surface"][d].get(s, [])) for d in single)) for s in rates}}
        r["halo_total"] = sum(r["single"]["halo"].values()) + sum(row["halo"] for row in r["rows"])
        print(label, r["single"], "halo", r["halo_total"], flush=True)
    off = res["settings"]["off"]

    def further(a: dict, b: dict) -> bool:  # a level of ``a`` more than the slack further from 1 than ``b``'s
        return any(abs(x - 1) > abs(y - 1) + args.level_slack for s in b for x, y in zip(a[s], b[s]))

    ok = [k for k, r in res["settings"].items()
          if all(r["per_spp"][s]["relmse"] <= args.relmse_tolerance * off["per_spp"][s]["relmse"]
                 for s in off["per_spp"])
          and r["single"]["relmse_geomean"] <= args.relmse_tolerance * off["single"]["relmse_geomean"]
          and not further({s: v["level"] for s, v in r["per_spp"].items()},
                          {s: v["level"] for s, v in off["per_spp"].items()})
          and not further(r["single"]["level"], off["single"]["level"])]
    best = min(ok, key=lambda k: (res["settings"][k]["halo_total"], res["settings"][k]["score"]))
    res["chosen"] = best if res["settings"][best]["halo_total"] < off["halo_total"] else "off"
    res["command"] = " ".join(["python", "experiments/rae_rates.py", *sys.argv[1:]])
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=("arms", "continue", "level", "clamp", "match", "exact", "taa", "accumulate",
                                     "background", "match-frames", "single-sample"))
    ap.add_argument("--data", default="runs/rae_rates_data")
    ap.add_argument("--val-data", default="data/rae_library_val")
    ap.add_argument("--out", required=True)
    ap.add_argument("--arms", default="power,rate,linear", help=f"arms: comma list of {sorted(ARMS)}")
    ap.add_argument("--arm", default=None, help="continue: the arm to train further")
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--validate-every", type=int, default=100)
    ap.add_argument("--select", default="geomean", choices=sorted(SELECT),
                    help="what picks a run's best/ (jaxdenoise.train.SELECT; geomean_halo: the geometric mean "
                         "among the validations with no more halo pixels than the start's)")
    ap.add_argument("--seconds", type=float, default=None,
                    help="stop a training run after this many seconds of steps (checkpointed: run again to "
                         "resume; a device lease's limit)")
    ap.add_argument("--lr", type=float, default=3e-4, help="Adam's base rate (ramp-up then 1/sqrt(t), the "
                    "module's schedule; 3e-4: the earlier CPU fine-tunes')")
    ap.add_argument("--init", default="jaxdenoise/weights/rae-paper")
    ap.add_argument("--level-weight", type=float, default=1.0, help="level: the level term's weight")
    ap.add_argument("--spike-weight", type=float, default=0.0, help="level: the spike term's weight "
                    "(`rae.Config.spike_weight`; 0: off)")
    ap.add_argument("--train-accumulate", type=float, default=0.0, help="level: the share of sequence crops below "
                    "the accumulation's sample count trained on accumulated colour (`rae.Config.train_accumulate`)")
    ap.add_argument("--ema", type=float, default=0.0, help="level: the decay of the params' moving average that "
                    "validation, best/ and weights/ use (`jaxdenoise.train.TrainConfig.ema`; 0: off)")
    ap.add_argument("--seed", type=int, default=3, help="level: the crops' seed (the shipped run drew seed 0's)")
    ap.add_argument("--factors", default="0,1,1.5,2,3,4,8,16,32,64",
                    help="clamp: outlier-clamp factors to score, the first the reference (0: off)")
    ap.add_argument("--level-tolerance", type=float, default=0.005,
                    help="clamp: the largest change of a level (per channel and rate) a chosen factor may make")
    ap.add_argument("--sigmas", default="8,16,32", help="match: Gaussian sigmas (px) of the level match")
    ap.add_argument("--gains", default="1.1,1.2,1.3", help="match: gain limits of the level match")
    ap.add_argument("--spikes", default="4,8", help="match: outlier cut factors of the level match's target")
    ap.add_argument("--rate-spikes", default="", help="match: one sample's cut factors with match_spike_by_rate "
                    "(labels rN: a frame of n spp cut at 1 + (N - 1) / sqrt(n) times its median; default none, as "
                    "the shipped choice was made)")
    ap.add_argument("--output-cuts", default="0", help="match: whether the target is also cut against the output "
                    "(`match_output_cut`; comma list of 0 / 1, labels ending ' o' for 1; default 0, as the shipped "
                    "choices before 0.9.22 were made)")
    ap.add_argument("--relmse-tolerance", type=float, default=1.01,
                    help="match, single-sample: the largest validation RelMSE (match: geometric mean; single-sample: "
                    "per rate and the single frames' geometric mean) a chosen setting may have, times off's")
    ap.add_argument("--rate-tolerance", type=float, default=1.10,
                    help="match: the largest validation RelMSE at any one rate a chosen setting may have, times off's")
    ap.add_argument("--windows", default="3,5,7", help="exact: the window rule's squares to score")
    ap.add_argument("--exact-data", default="data/procedural_val,data/library_val,data/library_val2",
                    help="exact, single-sample: validation folders of single frames scored beside the fly-throughs")
    ap.add_argument("--alphas", default="0.5,0.25,0.1", help="taa: blend weights (1 / the longest history)")
    ap.add_argument("--taa-windows", default="0,3", help="taa: clamp neighbourhoods (0: no clamp)")
    ap.add_argument("--tolerances", default="0,0.02,0.1", help="taa, accumulate, match-frames: tangent-plane "
                    "tolerances (0: no test)")
    ap.add_argument("--samples", default="2,4,8,16", help="accumulate: samples per pixel to accumulate up to (a "
                    "frame of n spp keeps at most S / n frames)")
    ap.add_argument("--match-frames", default="2,4,8,16", help="match-frames: the longest histories of the level "
                    "match's gain, in frames")
    ap.add_argument("--rel-sds", default="0.6,0.8,1", help="single-sample: relative standard errors at and above "
                    "which a pixel's outlier clamp drops its floor (`outlier_rel_sd`)")
    ap.add_argument("--clamps", default="2,4,8", help="accumulate: the history's clamp factors (0: none)")
    ap.add_argument("--level-slack", type=float, default=0.02,
                    help="taa, accumulate, background, match-frames, single-sample: how much further from 1 than "
                    "off's a chosen setting's level may be (every rate, channel)")
    ap.add_argument("--taa-data", default="data/rae_library_val2",
                    help="taa: more validation fly-throughs scored beside --val-data (comma list; '' for none)")
    args = ap.parse_args()
    if args.ema and args.what != "level":
        raise SystemExit(f"--ema is a setting of 'level' runs; '{args.what}' does not take it")
    out = Path(args.out)
    if args.what in ("taa", "accumulate", "background", "match-frames"):
        res = choose_temporal(args)
        write_json(out / f"{args.what}.json", res)
        print("chosen:", res["chosen"])
        return
    if args.what == "single-sample":
        res = choose_single_sample(args)
        write_json(out / "single_sample.json", res)
        print("chosen:", res["chosen"])
        return
    if args.what == "exact":
        res = choose_exact(args)
        write_json(out / "exact_pixels.json", res)
        print("chosen:", res["chosen"])
        return
    if args.what == "match":
        res = choose_match(args)
        write_json(out / "level_match.json", res)
        print("chosen:", res["chosen"])
        return
    if args.what == "clamp":
        res = choose_clamp(args)
        write_json(out / "outlier_clamp.json", res)
        print("chosen:", res["chosen"])
        return
    arms = args.arms.split(",") if args.what == "arms" else ["rate"] if args.what == "level" else [args.arm]
    bad = [a for a in arms if a not in ARMS]
    if bad:
        raise SystemExit(f"unknown arm(s) {bad}; expected some of {sorted(ARMS)}")
    data = load_data(_method(arms[0]), args.data, progress=False)
    path = out / "summary.json"
    summary = json.loads(path.read_text()) if path.is_file() else {"data": args.data, "val_data": args.val_data,
                                                                   "lr": args.lr, "init": args.init, "runs": {}}
    for arm in arms:
        if args.what == "level":
            name = f"level{args.level_weight:g}_lr{args.lr:g}_s{args.seed}"
            extra = {"spike_weight": args.spike_weight} if args.spike_weight else {}
            name += f"_spike{args.spike_weight:g}" if extra else ""
            if args.train_accumulate:
                extra["train_accumulate"] = args.train_accumulate
                name += f"_acc{args.train_accumulate:g}"
            name += f"_ema{args.ema:g}" if args.ema else ""
            rec = _train_arm(arm, data, out, args, args.steps, name, level_weight=args.level_weight, **extra)
        else:
            name, rec = arm, _train_arm(arm, data, out, args, args.steps)
        summary["runs"][name] = rec | {"command": " ".join(["python", "experiments/rae_rates.py", *sys.argv[1:]])}
        write_json(path, summary)


if __name__ == "__main__":
    main()
