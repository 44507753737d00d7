"""Converged path-traced references, rendered in resumable chunks.

A reference of ``total_spp`` samples per pixel is the mean of ``total_spp / chunk_spp`` independent
``pt`` renders of ``chunk_spp`` spp each; chunk ``i`` uses seed ``scene.integrator.seed + i``. After every
chunk the running sum (float64) is checkpointed to ``<out>.ckpt.npz`` (written atomically), so a killed
run resumes where it stopped and produces bitwise the same image as an uninterrupted run (on the same
device). The final EXR carries header attributes ``spp`` (int), ``seed`` (base seed, int),
``config_hash`` (:func:`nrc.config.config_hash`) and ``scene_hash`` (:func:`nrc.config.scene_hash`); the
checkpoint is then deleted.

The EXR also stores the **medium mask** as its ``A`` channel: ``alpha = 1 - T``, the transmittance ``T``
of the camera rays through the medium (no scattering; pixel centres, midpoint quadrature with one-voxel
steps; :func:`nrc.render.preview.medium_alpha`). ``nrc.metrics.medium_mask(alpha)`` turns it into the
pixel set "where the reference sees the medium". :func:`read_reference` returns image, alpha and header.

**The reference's own noise.** The checkpoint also accumulates the per-pixel sum of squares of the
chunks, so the variance of the reference mean is known: ``Var(r_hat) = var_chunks / n_chunks``. A
render ``x`` independent of the reference has ``E[(x - r_hat)^2] = E[(x - r)^2] + Var(r_hat)``, so every
relative MSE measured against the reference is inflated by about ``rel_mse_floor = mean over pixels of
Var(r_hat) / (r_hat^2 + 0.01)``, stored in the header (``rel_mse_floor`` over all pixels,
``rel_mse_floor_medium`` over the medium mask; ``-1`` with a single chunk). Subtract it or state it.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR
import torch
from omegaconf import DictConfig
from tqdm import tqdm

from nrc.config import config_hash, resolve_device, scene_hash
from nrc.errors import ConfigError, NRCError
from nrc.io import read_exr, write_exr
from nrc.io.atomic import write_atomically
from nrc.render.preview import medium_alpha
from nrc.render.registry import make_renderer
from nrc.scene import Scene, load_scene

@dataclasses.dataclass
class Reference:
    """A reference read back from its EXR: ``image`` (H, W, 3), ``alpha`` (H, W) or ``None``, header ``attrs``."""

    image: np.ndarray
    alpha: np.ndarray | None
    attrs: dict

    @property
    def rel_mse_floor(self) -> float | None:
        v = self.attrs.get("rel_mse_floor")
        return None if v is None or v < 0 else float(v)

    @property
    def rel_mse_floor_medium(self) -> float | None:
        v = self.attrs.get("rel_mse_floor_medium")
        return None if v is None or v < 0 else float(v)


def write_reference_exr(path: str | Path, image: np.ndarray, alpha: np.ndarray | None, attrs: dict) -> None:
    """Write RGB (+ ``A`` = ``alpha`` when given) float32 with header ``attrs`` (ZIP compression)."""
    write_exr(path, image, attrs, alpha)


def read_reference(path: str | Path) -> Reference:
    """Read a reference EXR: RGB, the ``A`` channel as alpha (``None`` if absent) and the header attributes."""
    image, attrs = read_exr(path)
    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = f.channels()
        alpha = np.asarray(ch["A"].pixels, dtype=np.float32) if "A" in ch else None
    return Reference(image, alpha, attrs)


def reference_noise_floor(total: np.ndarray, total_sq: np.ndarray, n: int, alpha: np.ndarray | None,
                          eps: float = 0.01) -> tuple[float, float]:
    """``(all, medium)`` mean of ``Var(r_hat) / (r_hat^2 + eps)``; ``(-1, -1)`` when ``n < 2``."""
    if n < 2:
        return -1.0, -1.0
    mean = total / n
    var_chunk = np.maximum(total_sq / n - mean**2, 0.0) * n / (n - 1)
    term = var_chunk / n / (mean**2 + eps)
    med = -1.0
    if alpha is not None:
        from nrc.metrics import medium_mask

        m = medium_mask(alpha)
        med = float(term[m].mean()) if m.any() else -1.0
    return float(term.mean()), med


def checkpoint_path(out: str | Path) -> Path:
    """Where the checkpoint of a reference written to ``out`` lives: ``<out>.ckpt.npz``."""
    out = Path(out)
    return out.with_name(out.name + ".ckpt.npz")


def _load_checkpoint(
    path: Path, chash: str, chunk_spp: int, seed: int, n_chunks: int
) -> tuple[np.ndarray | None, np.ndarray | None, int]:
    """The running sum, sum of squares and number of chunks done from ``path`` (``(None, None, 0)`` if absent).

    Checks that the checkpoint matches the config and chunking.
    """
    if not path.is_file():
        return None, None, 0
    with np.load(path) as ck:
        saved = {k: ck[k] for k in ck.files}
    if str(saved["config_hash"]) != chash:
        raise NRCError(
            f"checkpoint {path} was rendered with a different scene/renderer/transmittance config "
            f"(hash {str(saved['config_hash'])[:12]}..., now {chash[:12]}...); delete it or use another --out"
        )
    if int(saved["chunk_spp"]) != chunk_spp or int(saved["seed"]) != seed:
        raise NRCError(
            f"checkpoint {path} used chunk_spp={int(saved['chunk_spp'])}, seed={int(saved['seed'])}; "
            f"resume with the same values (got chunk_spp={chunk_spp}, seed={seed}) or delete it"
        )
    done = int(saved["chunks_done"])
    if done > n_chunks:
        raise NRCError(f"checkpoint {path} already holds {done} chunks, more than the {n_chunks} requested")
    if "sum_sq" not in saved:
        raise NRCError(f"checkpoint {path} is from an older version (no sum of squares); delete it")
    return saved["sum"], saved["sum_sq"], done


def _save_checkpoint(
    path: Path, total: np.ndarray, total_sq: np.ndarray, done: int, chash: str, chunk_spp: int, seed: int
) -> None:
    """Write the checkpoint atomically (a kill mid-write leaves the previous one intact)."""
    write_atomically(path, lambda f: np.savez(f, sum=total, sum_sq=total_sq, chunks_done=done, config_hash=chash,
                                              chunk_spp=chunk_spp, seed=seed))


def _render_chunk(scene: Scene, cfg: DictConfig, chunk_spp: int, seed: int) -> np.ndarray:
    """One ``pt`` render of ``chunk_spp`` spp with ``seed``, as float64."""
    integ = dataclasses.replace(scene.integrator, spp=chunk_spp, seed=seed)
    chunk_scene = dataclasses.replace(scene, integrator=integ)
    return make_renderer("pt", chunk_scene, cfg).render().image.astype(np.float64)


def chunk_sums(scene: Scene, cfg: DictConfig, chunk_spp: int, seeds: Iterable[int], total: np.ndarray | None,
               total_sq: np.ndarray | None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Render the chunks of ``seeds`` in order, yielding the running sum and sum of squares (float64, ``(H, W,
    3)``) after each; ``total`` / ``total_sq`` are the sums of the chunks already done (None: none). Whoever
    consumes it saves its progress between chunks (a reference's checkpoint, a part's file)."""
    for seed in seeds:
        image = _render_chunk(scene, cfg, chunk_spp, seed)
        total = image if total is None else total + image
        total_sq = image**2 if total_sq is None else total_sq + image**2
        yield total, total_sq


def _chunk_count(chunk_spp: int, total_spp: int) -> int:
    if chunk_spp < 1 or total_spp < 1 or total_spp % chunk_spp:
        raise ConfigError(f"total spp ({total_spp}) must be a positive multiple of chunk spp ({chunk_spp})")
    return total_spp // chunk_spp


def render_reference(
    cfg: DictConfig,
    out: str | Path,
    chunk_spp: int,
    total_spp: int,
    progress: bool = True,
    stop_after: int | None = None,
) -> np.ndarray | None:
    """Render (or resume) a ``total_spp`` reference of ``cfg`` in chunks and write it to ``out`` (EXR).

    Args:
        cfg: the app config (``renderer.name`` must be ``pt``); ``scene.integrator.spp`` is ignored
            (``total_spp`` counts); ``scene.integrator.seed`` picks the base seed (:func:`reference_base_seed`:
            seeds below ``REF_SEED`` move into the reference stream, disjoint from every render's seeds).
        out: the EXR path; the checkpoint is ``<out>.ckpt.npz``.
        chunk_spp: spp per chunk; ``total_spp`` must be a multiple of it.
        progress: show a tqdm bar (with ETA) over chunks.
        stop_after: run at most this many chunks in this call (simulates a kill; the checkpoint stays).

    Returns:
        The ``(H, W, 3)`` float32 reference once complete, ``None`` if stopped early.
    """
    if cfg.renderer.name != "pt":
        raise ConfigError(f"references are rendered with renderer=pt, got renderer={cfg.renderer.name}")
    n_chunks = _chunk_count(chunk_spp, total_spp)
    if n_chunks > REF_SEEDS_PER_BASE:
        raise ConfigError(f"a reference takes at most {REF_SEEDS_PER_BASE} chunks, got {n_chunks}: raise --chunk-spp")
    out, seed, chash = Path(out), reference_base_seed(int(cfg.scene.integrator.seed)), config_hash(cfg)
    ckpt = checkpoint_path(out)
    total, total_sq, done = _load_checkpoint(ckpt, chash, chunk_spp, seed, n_chunks)
    scene = load_scene(cfg.scene, resolve_device(cfg.get("device", "cpu")))
    out.parent.mkdir(parents=True, exist_ok=True)
    end = n_chunks if stop_after is None else min(n_chunks, done + stop_after)
    # tqdm shows elapsed time and an ETA from the chunk rate
    with tqdm(total=n_chunks, initial=done, unit="chunk", desc=f"reference {out.name}", disable=not progress) as bar:
        sums = chunk_sums(scene, cfg, chunk_spp, range(seed + done, seed + end), total, total_sq)
        for i, (total, total_sq) in enumerate(sums, start=done):
            _save_checkpoint(ckpt, total, total_sq, i + 1, chash, chunk_spp, seed)
            bar.update(1)
    if end < n_chunks:
        return None
    reference = (total / n_chunks).astype(np.float32)
    alpha = medium_alpha(scene)
    floor_all, floor_med = reference_noise_floor(total, total_sq, n_chunks, alpha)
    attrs = {
        "spp": int(total_spp), "seed": seed, "config_hash": chash, "scene_hash": scene_hash(cfg),
        "chunk_spp": int(chunk_spp), "rel_mse_floor": floor_all, "rel_mse_floor_medium": floor_med,
        "alpha": "A channel: 1 - camera-ray transmittance through the medium",
    }
    write_reference_exr(out, reference, alpha, attrs)
    ckpt.unlink()
    return reference


REF_SEED = 1_000_000  # references draw seeds >= REF_SEED; every render they judge uses seeds below it
REF_SEEDS_PER_BASE = 10_000  # chunks a reference of one base seed may use


def reference_base_seed(seed: int) -> int:
    """The first chunk seed of a reference asked for with ``scene.integrator.seed = seed``: seeds below
    :data:`REF_SEED` are moved into the reference stream (``REF_SEED + seed * REF_SEEDS_PER_BASE``), so a
    reference never repeats the random numbers of a render with the same nominal seed (chunk ``i`` uses
    ``base + i``)."""
    if seed < 0:
        raise ConfigError(f"scene.integrator.seed must be >= 0 for a reference, got {seed}")
    return seed if seed >= REF_SEED else REF_SEED + seed * REF_SEEDS_PER_BASE


def reference_seed_range(attrs: dict) -> range:
    """The chunk seeds a reference EXR was rendered with (from its header ``seed``, ``spp``, ``chunk_spp``)."""
    seed, spp, chunk = int(attrs.get("seed", 0)), int(attrs.get("spp", 1)), int(attrs.get("chunk_spp", 1))
    return range(seed, seed + max(1, spp // max(1, chunk)))


def check_independent(attrs: dict, seeds, path: str | Path = "the reference") -> None:
    """Refuse to judge renders with seeds that overlap the reference's own (correlated errors would cancel)."""
    used = reference_seed_range(attrs)
    overlap = sorted({int(s) for s in seeds} & set(used))
    if overlap or any(int(s) >= REF_SEED for s in seeds):
        shown = overlap[:3] or [s for s in seeds if int(s) >= REF_SEED][:3]
        raise ConfigError(f"{path} was rendered with seeds {used.start}..{used.stop - 1}; the compared renders "
                          f"use seed(s) {shown} from the reference stream (>= {REF_SEED}): not independent")
REFERENCE_ENV = "NRC_REFERENCE_DIR"  # where references are kept (a shared path on a cluster)


def reference_dir() -> Path:
    """Where references are kept by default: ``$NRC_REFERENCE_DIR`` (a shared path on a cluster), else
    ``data/references/`` under the current working directory (the repo root, where the scripts and the
    reference app run)."""
    given = os.environ.get(REFERENCE_ENV)
    return Path(given).expanduser() if given else Path.cwd() / "data" / "references"


def default_reference_path(cfg: Any, spp: int) -> Path:
    """``<reference dir>/reference_<scene hash[:12]>_<spp>spp.exr`` (:func:`reference_dir`)."""
    return reference_dir() / f"reference_{scene_hash(cfg)[:12]}_{int(spp)}spp.exr"
