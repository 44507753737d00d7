"""The named points of the optical-depth measurements (``scripts/crossover_map.py``, ``scripts/learning_curve.py``):
the thick preset (``scene=thick``: the Disney cloud, albedo 0.99, g 0.85, sun + sky) at a few density scales and
albedos, each with the spp of its reference; a point's scene overrides, its optical depth, and the check that the
references exist before any job runs (a job never renders one)."""

from __future__ import annotations

import os

from lab import REPO

VDB = "../shared/data/wdas_cloud_sixteenth.vdb"  # relative to the repo root, where everything runs (results name no machine path)
# name -> (scene overrides on top of the thick preset, reference spp)
POINTS: dict[str, tuple[list[str], int]] = {
    "d0.35": (["scene.volume.density_scale=0.35"], 2048),
    "d0.6": (["scene.volume.density_scale=0.6"], 2048),
    "d2": (["scene.volume.density_scale=2"], 512),
    "d5": ([], 1024),
    "d10": (["scene.volume.density_scale=10"], 512),
    "d5_a0.95": (["scene.volume.albedo=0.95"], 1024),
    "d5_a1": (["scene.volume.albedo=1.0", "scene.integrator.max_scatter=2048"], 512),
}


def point_scene(name: str, width: int, height: int, tool: str) -> tuple[list[str], int]:
    """The scene overrides of point ``name`` at ``width`` x ``height`` and its reference spp; an unknown name is a
    ``SystemExit`` of ``tool`` listing the known ones."""
    if name not in POINTS:
        raise SystemExit(f"{tool}: unknown point {name!r} (known: {', '.join(POINTS)})")
    ovs, ref_spp = POINTS[name]
    return ["scene=thick", f"scene.volume.path={VDB}", f"scene.camera.width={width}",
            f"scene.camera.height={height}", *ovs], ref_spp


def optical_depth(overrides: list[str]) -> dict:
    """The median optical depth (plain and reduced) over the camera rays that see the medium, the albedo and the
    density scale of the scene ``overrides`` configure (``nrc.volume.optical_depth``)."""
    from lab.render import setup
    from nrc.volume.optical_depth import scene_optical_depth

    run = setup(overrides, absolute=True)
    cfg, scene = run.cfg, run.scene
    od = scene_optical_depth(scene)
    return {"tau_median": od.median, "tau_reduced_median": od.median_reduced, "albedo": scene.albedo,
            "density_scale": float(cfg.scene.volume.density_scale)}


def require_references(scenes: dict[str, tuple[list[str], int]], tool: str) -> None:
    """Refuse (``SystemExit`` of ``tool``, with the command that renders it) a point of ``scenes`` (name -> (scene
    overrides, reference spp)) whose reference is missing: jobs never render one."""
    from nrc.config import compose
    from nrc.evaluation.reference import default_reference_path

    for name, (scene, ref_spp) in scenes.items():
        ref = default_reference_path(compose(scene), ref_spp)
        if not ref.is_file():
            raise SystemExit(f"{tool}: point {name} has no reference {os.path.relpath(ref, REPO)}: render it "
                             f"first, e.g. python -m nrc.reference_app {' '.join(scene)} "
                             f"scene.integrator.spp={ref_spp} (docs/running.md)")
