"""Light-sampling modes against each other: efficiency from the variance over independent renders.

For each scene type and each mode (``renderer.light_selection``, ``renderer.point_light_sampling``), ``--seeds``
independent renders of ``--spp`` samples per pixel are made in one process; the per-pixel variance over them,
relative to ``mean^2 + 0.01`` and averaged over the medium's pixels (where the pooled mean of all modes
exceeds 1e-3), is the relative variance ``relvar`` of one render; seconds per render are the median of the
renders' tracer set-up and render (the scene's loading, the same for every mode, is not counted). Every mode is unbiased, so ``relvar`` is its
expected relMSE against an exact reference; efficiency = 1 / (relvar x seconds per render), reported relative
to the scene's first mode. The image mean of each mode over its renders (with its standard error) shows that
the modes agree. No reference is needed, so heavy-tailed scenes cost no 1000-spp reference -- but note that
for an estimator of infinite variance (next-event estimation with medium at a point light) the sample
variance underestimates the truth: the rare huge samples are missing from a few renders.

    python scripts/bench_light_sampling.py [--scenes many_lights,lantern,...] [--seeds 8] [--spp 8]
        [--out docs/results/light_sampling_bench]

Writes ``bench.json`` and ``bench.md`` to ``--out``. Scene types: ``many_lights`` (16 point lights below the
cloud and a dim sky; uniform, power, ris with 4 and 8 candidates), ``sun_sky`` and ``cumulus`` (the two-light
scene types: uniform, power, ris), ``lantern`` (a point light inside the cloud; none against equiangular, at the
preset's density 0.6 and thinned to 0.1), ``lantern_pocket`` (the same light in a 4-unit pocket of clear air).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from lab import REPO
from lab.machine import machine
from lab.render import setup

from nrc.config import code_version  # noqa: E402
from nrc.volume.procedural import clear_pocket  # noqa: E402

LANTERN = (5.0, -20.0, 10.0)  # conf/scene/lantern.yaml
RIS = ["renderer.light_selection=ris"]
EQ = ["renderer.point_light_sampling=equiangular"]
# scene type -> (scene overrides, {mode: overrides})
SCENES = {
    "many_lights": (["scene=many_lights"], {"uniform": [], "power": ["renderer.light_selection=power"],
                                            "ris4": [*RIS, "renderer.ris.candidates=4"],
                                            "ris8": [*RIS, "renderer.ris.candidates=8"]}),
    "sun_sky": (["scene=sun_sky"], {"uniform": [], "power": ["renderer.light_selection=power"], "ris4": RIS}),
    "cumulus": (["scene=sun"], {"uniform": [], "power": ["renderer.light_selection=power"], "ris4": RIS}),
    "lantern": (["scene=lantern"], {"none": [], "equiangular": EQ}),
    "lantern_thin": (["scene=lantern", "scene.volume.density_scale=0.1"], {"none": [], "equiangular": EQ}),
    "lantern_pocket": (["scene=lantern", "scene.volume.density_scale=0.1", "POCKET"], {"none": [], "equiangular": EQ}),
}


def pocket_overrides(out: Path) -> list[str]:
    """The lantern's cloud with a 4-unit pocket of clear air around the light, as an ``.npz`` in ``outputs/``."""
    path = REPO / "outputs" / "lantern_pocket.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.is_file():
        grid = setup(["scene=lantern"]).scene.grid
        np.savez(path, density=clear_pocket(grid, LANTERN, 4.0).numpy())
    return ["scene.volume.source=npz", f"scene.volume.path={path}"]


def run_scene(name: str, args, out: Path) -> dict:
    scene_ov, modes = SCENES[name]
    scene_ov = [o for o in scene_ov if o != "POCKET"] + (pocket_overrides(out) if "POCKET" in scene_ov else [])
    base = ["renderer=pt", f"renderer.backend={args.backend}", *scene_ov, f"scene.camera.width={args.width}",
            f"scene.camera.height={args.height}", f"scene.integrator.spp={args.spp}"]
    renders, seconds = {}, {}
    for mode, ov in modes.items():
        ims, t = [], []
        for seed in range(args.seeds):
            run = setup([*base, *ov, f"scene.integrator.seed={1000 + seed}"])  # not timed: the same cloud for every mode
            t0 = time.perf_counter()
            ims.append(run.renderer().render().image.mean(-1))
            t.append(time.perf_counter() - t0)
        renders[mode], seconds[mode] = np.stack(ims), float(np.median(t))
        if not args.quiet:
            print(f"{name:15s} {mode:12s} {seconds[mode]:.2f} s/render", flush=True)
    pooled = np.mean([a.mean(0) for a in renders.values()], axis=0)
    mask = pooled > 1e-3
    rows, first = {}, None
    for mode, a in renders.items():
        relvar = float((a.var(0, ddof=1) / (pooled ** 2 + 0.01))[mask].mean())
        eff = 1.0 / (relvar * seconds[mode])
        first = first or eff
        means = a.mean((1, 2))
        rows[mode] = {"relvar": relvar, "seconds": seconds[mode], "efficiency": eff, "vs_first": eff / first,
                      "mean": float(means.mean()), "mean_se": float(means.std(ddof=1) / np.sqrt(len(means))),
                      "max_pixel": float(a.max())}
    return {"overrides": scene_ov, "modes": {m: o for m, o in modes.items()}, "medium_pixels": int(mask.sum()),
            "rows": rows}


def markdown(res: dict, meta: dict) -> str:
    lines = [f"Light-sampling modes, {meta['width']}x{meta['height']}, {meta['spp']} spp per render, {meta['seeds']} "
             f"renders per mode, backend {meta['backend']}; {meta['machine']}; {meta['git']}. relvar: per-pixel "
             "variance over the renders / (mean^2 + 0.01), medium pixels; efficiency = 1 / (relvar x s/render), "
             "relative to each scene's first mode (scripts/bench_light_sampling.py).", "",
             "| scene | mode | s/render | relvar | efficiency vs first | image mean | max pixel |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for scene, r in res.items():
        for mode, row in r["rows"].items():
            lines.append(f"| {scene} | {mode} | {row['seconds']:.2f} | {row['relvar']:.3g} | {row['vs_first']:.2f}x | "
                         f"{row['mean']:.4g} +- {row['mean_se']:.2g} | {row['max_pixel']:.3g} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", default=",".join(SCENES))
    p.add_argument("--seeds", type=int, default=8)
    p.add_argument("--spp", type=int, default=8)
    p.add_argument("--width", type=int, default=80)
    p.add_argument("--height", type=int, default=45)
    p.add_argument("--backend", default="eager", choices=["eager", "compiled"])
    p.add_argument("--out", type=Path, default=REPO / "outputs" / "light_sampling_bench")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    names = [n for n in args.scenes.split(",") if n]
    unknown = [n for n in names if n not in SCENES]
    if unknown:
        raise SystemExit(f"bench_light_sampling: unknown scene(s) {', '.join(unknown)}; known: {', '.join(SCENES)}")
    if args.seeds < 2:
        raise SystemExit("bench_light_sampling: --seeds must be >= 2 (the variance is over renders)")
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    res = {n: run_scene(n, args, args.out) for n in names}
    meta = {"width": args.width, "height": args.height, "spp": args.spp, "seeds": args.seeds, "backend": args.backend,
            "machine": machine(),
            "git": code_version(), "wall_s": time.perf_counter() - t0, "argv": sys.argv[1:]}
    for r in res.values():  # paths relative to the checkout
        r["overrides"] = [o.replace(str(REPO) + "/", "") for o in r["overrides"]]
    (args.out / "bench.json").write_text(json.dumps({"meta": meta, "scenes": res}, indent=2))
    (args.out / "bench.md").write_text(markdown(res, meta))
    print(markdown(res, meta))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
