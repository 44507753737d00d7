"""The Hydra application: ``python -m nrc [overrides]`` (or the ``nrc`` console script).

Loads and validates the scene, renders with the configured renderer and writes, into Hydra's run
directory: ``image.exr`` (linear float32 RGB), ``preview.png`` (tone-mapped) and ``metrics.json``.
Configuration errors print one message naming the key and exit with status 2 (no traceback).
"""

from __future__ import annotations

import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from nrc.config import CONF_DIR, absolute_paths, resolve_device
from nrc.errors import NRCError

log = logging.getLogger("nrc")


def run(cfg: DictConfig, out_dir: Path) -> dict[str, Any]:
    """Render the configured scene and write the outputs into ``out_dir``; returns the metrics."""
    from nrc.io import write_exr, write_png
    from nrc.io.png import DisplaySettings
    from nrc.render.registry import make_renderer
    from nrc.scene import load_scene

    display = DisplaySettings.from_config(cfg)
    t0 = time.perf_counter()
    device = resolve_device(cfg.device)
    scene = load_scene(cfg.scene, device)
    t_load = time.perf_counter() - t0
    renderer = make_renderer(cfg.renderer.name, scene, cfg)
    if hasattr(renderer, "attach_output"):  # renderers with logs and checkpoints (nrc) write them to the run dir
        renderer.attach_output(out_dir)
    result = renderer.render(progress=True)
    image = np.nan_to_num(result.image, nan=0.0, posinf=0.0, neginf=0.0)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_exr(out_dir / "image.exr", image)
    exposure = display.exposure_for(image)
    write_png(out_dir / "preview.png", image, exposure, display.tonemap)
    metrics = {"time_scene_load_s": t_load, **result.metrics, "device": str(device),
               "preview": {"tonemap": display.tonemap, "exposure": exposure}}
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
    log.info("wrote %s (image.exr, preview.png, metrics.json)", out_dir)
    return metrics


@hydra.main(config_path=CONF_DIR, config_name="config", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    try:
        absolute_paths(cfg)
        run(cfg, Path(HydraConfig.get().runtime.output_dir))
    except NRCError as exc:
        print(f"nrc: error: {exc}", file=sys.stderr)
        sys.exit(2)


def main() -> None:
    """Console-script entry point."""
    _hydra_main()


if __name__ == "__main__":
    main()
