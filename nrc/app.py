"""The Hydra application: ``python -m nrc [overrides]`` (or the ``nrc`` console script).

Loads and validates the scene, renders with the configured renderer and writes, into Hydra's run
directory: ``image.exr`` (linear float32 RGB, alpha = the medium's opacity along each pixel's camera ray,
header metadata), ``preview.png`` (tone-mapped) and ``metrics.json``; with ``denoise=oidn`` also
``image_denoised.exr`` and ``preview_denoised.png`` (:mod:`nrc.denoise`).
Configuration errors print one message naming the key and exit with status 2 (no traceback). Settings that
are ignored in this configuration print one warning each. NaN/Inf pixels are kept in ``image.exr``, shown
magenta in the preview, counted in ``metrics.json`` (``nonfinite_pixels``) and warned about.
A SIGINT or SIGTERM during ``renderer=nrc`` finishes the current frame, writes the checkpoint and the
outputs of the frames done, prints the command that resumes, and exits with 130 (SIGINT) or 143 (SIGTERM).
"""

from __future__ import annotations

import json
import logging
import os
import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from nrc.config import CONF_DIR, absolute_paths, code_version, resolve_device
from nrc.errors import NRCError
from nrc.io.atomic import write_text_atomically

log = logging.getLogger("nrc")


def ignored_settings(cfg: DictConfig) -> list[str]:
    """Warnings for settings that have no effect in this configuration (conflicts are errors of the typed
    settings, e.g. ``renderer.accumulate`` with an animation)."""
    warnings = []
    name = cfg.renderer.get("name")
    if name != "nrc" and cfg.get("frames", 30) != 30:
        warnings.append(f"frames={cfg.frames} is ignored by renderer={name} (it renders one image; frames are "
                        "for renderer=nrc)")
    vol = cfg.scene.get("volume")
    if OmegaConf.is_dict(vol) and vol.get("source") == "procedural" and vol.get("path"):
        warnings.append(f"scene.volume.path={vol.path} is ignored with scene.volume.source=procedural (set "
                        "scene.volume.source=vdb or npz to read it)")
    lights = cfg.scene.get("lights")
    if OmegaConf.is_list(lights) and len(lights) == 0 and name != "preview":
        warnings.append("scene.lights is empty (scene=base has none): the image will be black; pick a preset "
                        "such as scene=sun")
    return warnings


def preflight(cfg: DictConfig) -> tuple[Any, Any, str]:
    """Every value that can be checked before any work starts, in one place (one ``ConfigError`` / ``NRCError``
    naming the key or file): ``frames``, ``device``, the display and denoise settings, the renderer's typed settings
    (:func:`nrc.render.registry.renderer_settings`: for NRC also ``frames``, the batch filter, the transmittance
    estimator and the cache groups), and the files the run will read (the volume, environment maps,
    ``renderer.reference`` and ``renderer.resume``). The scene's own values are checked by ``load_scene`` as it
    builds them. Returns what the run uses, each read once: the renderer's settings (their ``auto`` rules resolved
    later, on the loaded scene), the display settings and the denoiser."""
    from nrc.config import ConfigReader
    from nrc.denoise import denoiser_from_config
    from nrc.errors import ConfigError
    from nrc.io.png import DisplaySettings
    from nrc.render.registry import renderer_settings

    ConfigReader({"frames": cfg.get("frames")}, "").get_int("frames", 30, lo=1)  # renderers other than nrc ignore it
    resolve_device(cfg.get("device", "cpu"))
    renderer = cfg.get("renderer")
    if not OmegaConf.is_dict(renderer):
        raise ConfigError(f"renderer must be a config block (renderer=pt|nrc|preview), got {renderer!r}")
    settings = renderer_settings(renderer.get("name"), cfg)
    display = getattr(settings, "display", None) or DisplaySettings.from_config(cfg)  # NRC's settings hold it
    denoiser = denoiser_from_config(cfg)
    files = []
    scene = cfg.get("scene")
    vol = scene.get("volume") if OmegaConf.is_dict(scene) else None
    if OmegaConf.is_dict(vol) and vol.get("source") in ("vdb", "npz") and isinstance(vol.get("path"), str) \
            and vol.get("path"):
        files.append(("scene.volume.path", vol.path))
    lights = scene.get("lights") if OmegaConf.is_dict(scene) else None
    for i, light in enumerate(lights if OmegaConf.is_list(lights) else []):
        if OmegaConf.is_dict(light) and isinstance(light.get("path"), str) and light.get("path"):
            files.append((f"scene.lights[{i}].path", light.path))
    for key in ("reference", "resume"):
        if isinstance(renderer.get(key), str) and renderer.get(key):
            files.append((f"renderer.{key}", renderer[key]))
    for key, path in files:
        if not Path(path).is_file():
            what = "no such file" if not Path(path).exists() else "not a file"
            raise ConfigError(f"{key}={path}: {what}")
    return settings, display, denoiser


def _write(what: str, path: Path, write: Any) -> None:
    try:
        write()
    except (OSError, ValueError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc).splitlines()[0]
        raise NRCError(f"cannot write {what} {path}: {reason}") from None


@dataclass
class Job:
    """A configured render, built and not yet run (:func:`prepare`): the scene, the renderer and what the outputs
    need. ``out_dir`` is None when nothing is written (the Python API without a run directory)."""

    cfg: DictConfig
    scene: Any
    renderer: Any
    display: Any
    denoiser: str
    out_dir: Path | None
    threads: int
    time_scene_load_s: float


@dataclass
class Outcome:
    """A finished render: the linear image (H, W, 3) float32, its metrics (``metrics.json``) and, with
    ``denoise=oidn``, the denoised image."""

    image: np.ndarray
    metrics: dict[str, Any]
    denoised: np.ndarray | None


def prepare(cfg: DictConfig, out_dir: Path | None) -> Job:
    """Check the config and read the settings once (:func:`preflight`), set the threads (``threads``), load the
    scene, resolve the settings' ``auto`` rules on it and build the renderer from them; with ``out_dir`` the
    renderer writes its logs and checkpoints there."""
    from nrc.config import apply_threads
    from nrc.render.registry import build_renderer, resolve_settings
    from nrc.scene import load_scene

    settings, display, denoiser = preflight(cfg)
    threads = apply_threads(cfg.get("threads", "auto"))
    for warning in ignored_settings(cfg):
        log.warning(warning)
    if out_dir is not None:
        out_dir = Path(out_dir)
        if out_dir.exists() and not out_dir.is_dir():
            raise NRCError(f"the run directory {out_dir} is a file, not a directory")
        for name in ("image.exr", "preview.png", "metrics.json"):
            if (out_dir / name).is_dir():
                raise NRCError(f"cannot write {out_dir / name}: a directory of that name is in the way")
    t0 = time.perf_counter()
    device = resolve_device(cfg.device)
    scene = load_scene(cfg.scene, device)
    t_load = time.perf_counter() - t0
    renderer = build_renderer(cfg.renderer.name, scene, resolve_settings(settings, scene))
    if out_dir is not None and hasattr(renderer, "attach_output"):  # logs and checkpoints (nrc) go to the run dir
        renderer.attach_output(out_dir)
    return Job(cfg, scene, renderer, display, denoiser, out_dir, threads, t_load)


def finish(job: Job, result: Any) -> Outcome:
    """The metrics and the denoised image of a render, and (with ``job.out_dir``) the outputs written."""
    from nrc.config import config_hash
    from nrc.render.preview import medium_alpha
    from nrc.io import write_exr, write_png

    from nrc.denoise import clamp_bias, denoise, oidn_version

    cfg, scene, display, out_dir = job.cfg, job.scene, job.display, job.out_dir
    image = np.asarray(result.image, dtype=np.float32)
    nonfinite = int((~np.isfinite(image)).any(axis=-1).sum())
    if nonfinite:
        log.warning("%d pixels are NaN/Inf: kept in image.exr, magenta in preview.png", nonfinite)
    exposure = display.exposure_for(image)
    metrics = {"time_scene_load_s": job.time_scene_load_s, **result.metrics, "device": str(scene.device),
               "threads": job.threads, "nonfinite_pixels": nonfinite,
               "preview": {"tonemap": display.tonemap, "exposure": exposure}, "code": code_version()}
    attrs = {"renderer": str(cfg.renderer.name), "spp": int(scene.integrator.spp),
             "seed": int(scene.integrator.seed), "config_hash": config_hash(cfg), "code": metrics["code"],
             "alpha": "A channel: 1 - camera-ray transmittance through the pixel centre (the expected fraction "
                      "of camera samples with a real collision)"}
    if cfg.renderer.name == "nrc":
        attrs["frames"] = int(metrics.get("frames_done", cfg.frames))
    outputs = {"image.exr": ("the image", image, attrs), "preview.png": ("the preview", image, None)}
    denoised = None
    if job.denoiser == "oidn":  # before anything is written: metrics.json then holds the denoise time
        t0 = time.perf_counter()
        denoised = denoise(image)
        metrics["time_denoise_s"] = time.perf_counter() - t0
        metrics["denoise"] = oidn_version()
        metrics["denoise_clamp_bias"] = clamp_bias(image)  # what cleaning negative pixels adds to the mean
        outputs["image_denoised.exr"] = ("the denoised image", denoised, {**attrs, "denoiser": metrics["denoise"]})
        outputs["preview_denoised.png"] = ("the denoised preview", denoised, None)
    if out_dir is None:
        return Outcome(image, metrics, denoised)
    _write("the run directory", out_dir, lambda: out_dir.mkdir(parents=True, exist_ok=True))
    alpha = medium_alpha(scene)
    for name, (what, img, header) in outputs.items():
        path = out_dir / name
        if name.endswith(".exr"):
            _write(what, path, lambda: write_exr(path, img, header, alpha))
        else:
            _write(what, path, lambda: write_png(path, img, exposure, display.tonemap))
    _write("the metrics", out_dir / "metrics.json",
           lambda: (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2)))
    written = [*outputs, "metrics.json"]
    if metrics.get("checkpoint"):
        written.append(f"checkpoint.pt (frame {metrics['checkpoint_frame']}, "
                       f"{metrics['checkpoint_bytes'] / 1e6:.1f} MB)")
    tb = metrics.get("tensorboard_dir")
    if tb and Path(tb) != out_dir / "tensorboard":  # a resumed run continues the curves of the run it resumes
        written.append(f"TensorBoard logs continued in {tb}")
    elif (out_dir / "tensorboard").is_dir():
        written.append("tensorboard/")
    log.info("wrote %s: %s", out_dir, ", ".join(written))
    return Outcome(image, metrics, denoised)


def execute(cfg: DictConfig, out_dir: Path | None, progress: bool = True) -> Outcome:
    """Render the configured scene; with ``out_dir`` write the outputs there (``python -m nrc`` and
    ``nrc.render`` both run this)."""
    job = prepare(cfg, out_dir)
    return finish(job, job.renderer.render(progress=progress))


def run(cfg: DictConfig, out_dir: Path) -> dict[str, Any]:
    """Render the configured scene and write the outputs into ``out_dir``; returns the metrics."""
    return execute(cfg, Path(out_dir)).metrics


def sweep_jobs(config: DictConfig) -> list[list[str]]:
    """The override lists of a multirun's jobs (Hydra's basic sweeper: the cartesian product of the swept values),
    from the sweep's config (``hydra.overrides.task``)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides(list(config.hydra.overrides.task))
    return [job for batch in BasicSweeper.split_arguments(parsed, None) for job in batch]


def concurrent_jobs(launcher: DictConfig, n_jobs: int, cores: int) -> int | None:
    """How many of a sweep's ``n_jobs`` jobs its launcher runs at once on this machine: joblib's ``n_jobs`` (``-1``
    all cores, ``-k`` all but k - 1), ``submitit_local`` all of them; None for launchers that run one job at a time
    in this process (the basic launcher: a job takes this process's threads) or on other machines (Slurm grants a
    job its cores: ``threads=auto`` reads ``$SLURM_CPUS_PER_TASK``)."""
    target = str(launcher.get("_target_", ""))
    if target.endswith("JoblibLauncher"):
        given = int(launcher.get("n_jobs", -1))
        workers = given if given > 0 else max(1, cores + 1 + given)
        return max(1, min(workers, n_jobs))
    if target.endswith("submitit_launcher.LocalLauncher"):
        return max(1, n_jobs)
    return None


class SweepSetup(Callback):
    """A parallel sweep on this machine (joblib, ``submitit_local``), before its jobs start, in the launching
    process: each job is granted ``cores / jobs at once`` threads (``$NRC_THREADS``, which ``threads=auto`` reads;
    a job's explicit ``threads=N`` wins), and the compiled step of every structure the jobs use is built once for
    that thread count (a tiny render of each job with ``renderer.backend=compiled``), so that no worker compiles
    it again, and ``renderer.backend=auto`` in a worker finds it (a load of milliseconds) instead of rendering
    eagerly. Jobs with ``renderer.backend=eager``, on another device, or whose config is invalid (the job itself
    reports it) are skipped."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        from nrc.config import THREADS_ENV

        try:
            jobs = sweep_jobs(config)
        except Exception as exc:  # noqa: BLE001 -- the sweeper reports a bad sweep in its own words
            log.info("sweep setup skipped: %s", exc)
            return
        cores = default_threads()
        at_once = concurrent_jobs(config.hydra.launcher, len(jobs), cores)
        if at_once is None:
            return
        os.environ.setdefault(THREADS_ENV, str(max(1, cores // at_once)))
        log.info("sweep: %d jobs, %d at once, %s threads each", len(jobs), at_once, os.environ[THREADS_ENV])
        try:
            prebuild_steps(jobs)
        finally:
            if "torch" in sys.modules:  # imported only to build a step (a sweep whose steps are known loads none)
                sys.modules["torch"].set_num_threads(cores)


def default_threads() -> int:
    """torch's default thread count in this process (the cores it may use, or ``OMP_NUM_THREADS``), without
    importing torch where a sweep on this machine recorded it (``sweep-steps.json``, keyed by the node, the CPUs
    this process may use and the thread variables): the launching process of a sweep whose steps are known then
    imports no torch, which its workers import anyway."""
    import platform

    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    key = repr((platform.node(), cpus, os.environ.get("OMP_NUM_THREADS"), os.environ.get("MKL_NUM_THREADS")))
    path, memo = _known_steps()
    known = memo.get("threads", {})
    if isinstance(known, dict) and isinstance(known.get(key), int):
        return known[key]
    import torch

    n = torch.get_num_threads()
    _record(path, {"threads": {**(known if isinstance(known, dict) else {}), key: n}})
    return n


PREBUILD_OVERRIDES = ("scene.camera.width=8", "scene.camera.height=4", "scene.integrator.spp=1", "frames=1",
                      "denoise=none", "renderer.backend=compiled")


def step_of(cfg: DictConfig) -> tuple[tuple[Any, ...], bool, tuple[Path, ...] | None]:
    """The key of the transport step structure ``cfg``'s renderer compiles (one compiled step per key and thread
    count), whether its AOT packages for this process's thread count are in the cache already, and their files
    (None where the step is not packaged): its renderer built, nothing rendered."""
    from nrc.render.registry import make_renderer
    from nrc.render.wavefront.machine import aot_packages, packages_cached
    from nrc.scene import load_scene

    device = resolve_device(cfg.device)
    renderer = make_renderer(cfg.renderer.name, load_scene(cfg.scene, device), cfg)
    core = renderer.core if hasattr(renderer, "core") else renderer.tracer.core
    return (core.step.key, packages_cached(core.step, core.steps_per_call, device),
            aot_packages(core.step, core.steps_per_call, device))


def _known_steps() -> tuple[Path, dict[str, Any]]:
    """The sweeps' memory (``<compile cache>/nrc-aot/sweep-steps.json``, torch-free to read): which packages a
    job's config needs (a hash of the tiny config, the thread count, torch's version and the step's sources -> the
    package files), so that a sweep run again finds its steps without building a renderer per job; and torch's
    default thread count per machine (``threads``, :func:`default_threads`)."""
    from nrc.render.compile_cache import inductor_cache_dir

    path = inductor_cache_dir() / "nrc-aot" / "sweep-steps.json"
    try:
        memo = json.loads(path.read_text())
        return path, memo if isinstance(memo, dict) else {}
    except (OSError, ValueError):
        return path, {}


def _record(path: Path, updates: dict[str, Any]) -> None:
    """Add ``updates`` to the sweeps' memory (read again first: another sweep may have written it), atomically."""
    try:
        memo = json.loads(path.read_text()) if path.is_file() else {}
        memo = {**(memo if isinstance(memo, dict) else {}), **updates}
        write_text_atomically(path, json.dumps(memo, indent=1))
    except (OSError, ValueError) as exc:  # a read-only cache: the next sweep finds out again
        log.info("sweep setup: could not record the steps (%s)", exc)


def _known_key(tiny: DictConfig, threads: int) -> str:
    import hashlib
    from importlib.metadata import PackageNotFoundError, version

    from nrc.render.compile_cache import package_sources

    try:
        torch_version = version("torch")
    except PackageNotFoundError:  # a source build without metadata: torch itself knows
        import torch

        torch_version = torch.__version__
    text = OmegaConf.to_yaml(tiny, resolve=True) + repr((threads, torch_version, package_sources()))
    return hashlib.sha1(text.encode()).hexdigest()


def prebuild_steps(jobs: list[list[str]]) -> None:
    """Build (or load) the compiled step of each structure the jobs use, at the job's thread count, by a tiny render
    of the first job of each (:data:`PREBUILD_OVERRIDES`) in this process. A job whose packages a previous sweep
    recorded (:func:`_known_steps`) and which are still in the cache is skipped without building its renderer."""
    from nrc.config import apply_threads, compose, job_threads

    memo_path, memo = _known_steps()
    found: dict[str, list[str]] = {}
    seen = set()
    for job in jobs:
        overrides = [o for o in job if not o.startswith("reference.")]  # a reference job's own keys: pt underneath
        try:
            cfg = compose(overrides)
            absolute_paths(cfg)
            if cfg.renderer.get("name") not in ("pt", "nrc") or cfg.renderer.get("backend") == "eager" \
                    or not str(cfg.get("device", "cpu")).startswith("cpu"):
                continue
            threads = job_threads(cfg.get("threads", "auto"))
            tiny = compose([*overrides, *PREBUILD_OVERRIDES, f"threads={threads}"])
            absolute_paths(tiny)
            known = _known_key(tiny, threads)
            if isinstance(memo.get(known), list) and memo[known] and all(Path(p).is_file() for p in memo[known]):
                continue  # its packages are in the cache: a worker loads them
            apply_threads(threads)  # the packages are keyed by the thread count
            key, cached, paths = step_of(tiny)
            if (key, threads) not in seen and not cached:  # built by a tiny render (a cached one: only loaded)
                execute(tiny, None, progress=False)
            seen.add((key, threads))
            if paths is not None and all(p.is_file() for p in paths):
                found[known] = [str(p) for p in paths]
        except Exception as exc:  # noqa: BLE001 -- the job itself reports a bad config, in its own words
            log.info("sweep setup: no step built for %s (%s)", " ".join(overrides), exc)
    if found:
        _record(memo_path, found)


def resume_command(out_dir: Path) -> str:
    """The command line that continues this run from its checkpoint."""
    try:
        task = list(HydraConfig.get().overrides.task)
    except ValueError:  # not inside a Hydra job
        task = []
    task = [o for o in task if not o.lstrip("+~").startswith("renderer.resume=")]
    return shlex.join([sys.executable.rsplit("/", 1)[-1], "-m", "nrc", *task,
                       f"renderer.resume={Path(out_dir).resolve() / 'checkpoint.pt'}"])


class _Terminated(BaseException):
    """SIGTERM outside the NRC frame loop (which handles its own signals)."""


def _on_sigterm(signum: int, frame: Any) -> None:
    raise _Terminated()


@hydra.main(config_path=CONF_DIR, config_name="config", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    import signal

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        absolute_paths(cfg)
        metrics = run(cfg, out_dir)
    except NRCError as exc:
        print(f"nrc: error: {exc}", file=sys.stderr)
        sys.exit(2)
    except (KeyboardInterrupt, _Terminated) as exc:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # stopping: a second Ctrl-C must not end it with a traceback
        name, code = ("SIGINT", 130) if isinstance(exc, KeyboardInterrupt) else ("SIGTERM", 143)
        print(f"nrc: interrupted by {name} before the outputs were written (renderer={cfg.renderer.get('name')} "
              "renders in one pass; scripts/render_reference.py renders long images in resumable chunks)",
              file=sys.stderr)
        sys.exit(code)
    finally:
        signal.signal(signal.SIGTERM, previous)
    if metrics.get("interrupted"):
        code = {"SIGINT": 130, "SIGTERM": 143}.get(metrics["interrupted"], 1)
        print(f"nrc: interrupted by {metrics['interrupted']} after frame {metrics['frames_done']} of "
              f"{metrics['frames']}; resume with:\n  {resume_command(out_dir)}", file=sys.stderr)
        sys.exit(code)


def run_dir_problem(argv: list[str]) -> str | None:
    """Why Hydra could not create the run (or sweep) directory named on the command line (or the default
    ``outputs/`` under the current directory), or ``None``; checked before Hydra starts, which would otherwise
    fail with a traceback."""
    if any(a in ("-h", "--help", "--hydra-help", "--info", "-c", "--cfg", "--shell-completion", "-sc")
           or a.startswith(("--cfg=", "--info=")) for a in argv):
        return None  # nothing will be written
    key = "hydra.sweep.dir=" if any(a in ("-m", "--multirun") for a in argv) else "hydra.run.dir="
    given = [a.split("=", 1)[1] for a in argv if a.startswith(key)]
    target = Path(given[-1] if given else "outputs").expanduser()
    target = target if target.is_absolute() else Path.cwd() / target
    probe = target
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if probe == target and target.is_dir():
        return None if os.access(target, os.W_OK) else f"the run directory {target} is not writable"
    if not probe.is_dir():
        return f"cannot create the run directory {target}: {probe} is a file"
    if not os.access(probe, os.W_OK):
        return f"cannot create the run directory {target}: {probe} is not writable (set {key}<a writable path>)"
    if "$" in str(target):  # an interpolation Hydra resolves later: not a path to create here
        return None
    try:  # the run would create it anyway; some file systems refuse what os.access allows (/proc, read-only mounts)
        target.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"cannot create the run directory {target}: {exc.strerror or exc} (set {key}<a writable path>)"
    return None


def main() -> None:
    """Console-script entry point."""
    problem = run_dir_problem(sys.argv[1:])
    if problem is not None:
        print(f"nrc: error: {problem}", file=sys.stderr)
        sys.exit(2)
    _hydra_main()


if __name__ == "__main__":
    main()
