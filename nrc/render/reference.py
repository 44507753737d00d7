"""Converged path-traced references, rendered in resumable chunks.

A reference of ``total_spp`` samples per pixel is the mean of ``total_spp / chunk_spp`` independent
``pt`` renders of ``chunk_spp`` spp each; chunk ``i`` uses seed ``scene.integrator.seed + i``. After every
chunk the running sum (float64) is checkpointed to ``<out>.ckpt.npz`` (written atomically), so a killed
run resumes where it stopped and produces bitwise the same image as an uninterrupted run (on the same
device). The final EXR carries header attributes ``spp`` (int), ``seed`` (base seed, int) and
``config_hash`` (see :func:`config_hash`); the checkpoint is then deleted.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import os
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from nrc.app import resolve_device
from nrc.errors import ConfigError, NRCError
from nrc.io import write_exr
from nrc.render.pt import PathTracer
from nrc.scene import Scene, load_scene

HASHED_SECTIONS = ("scene", "renderer", "transmittance")
CHUNKED_KEYS = ("spp", "seed")  # scene.integrator keys that chunking changes: not hashed


def config_hash(cfg: DictConfig) -> str:
    """sha256 (hex) of the resolved ``scene``, ``renderer`` and ``transmittance`` sections.

    ``scene.integrator.spp`` and ``scene.integrator.seed`` are excluded (chunking changes them); keys are
    sorted, so the hash depends on values only, not on the order of overrides.
    """
    sections = {k: OmegaConf.to_container(cfg[k], resolve=True) for k in HASHED_SECTIONS if k in cfg}
    sections = copy.deepcopy(sections)
    for key in CHUNKED_KEYS:
        sections["scene"].get("integrator", {}).pop(key, None)
    text = json.dumps(sections, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def checkpoint_path(out: str | Path) -> Path:
    """Where the checkpoint of a reference written to ``out`` lives: ``<out>.ckpt.npz``."""
    out = Path(out)
    return out.with_name(out.name + ".ckpt.npz")


def _load_checkpoint(path: Path, chash: str, chunk_spp: int, seed: int, n_chunks: int) -> tuple[np.ndarray | None, int]:
    """The running sum and number of chunks done from ``path`` (``(None, 0)`` if absent); checks it matches."""
    if not path.is_file():
        return None, 0
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
    return saved["sum"], done


def _save_checkpoint(path: Path, total: np.ndarray, done: int, chash: str, chunk_spp: int, seed: int) -> None:
    """Write the checkpoint atomically (a kill mid-write leaves the previous one intact)."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        np.savez(f, sum=total, chunks_done=done, config_hash=chash, chunk_spp=chunk_spp, seed=seed)
    os.replace(tmp, path)


def _render_chunk(scene: Scene, cfg: DictConfig, chunk_spp: int, seed: int) -> np.ndarray:
    """One ``pt`` render of ``chunk_spp`` spp with ``seed``, as float64."""
    integ = dataclasses.replace(scene.integrator, spp=chunk_spp, seed=seed)
    chunk_scene = dataclasses.replace(scene, integrator=integ)
    return PathTracer(chunk_scene, cfg).render().image.astype(np.float64)


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
            (``total_spp`` counts), ``scene.integrator.seed`` is the base seed.
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
    out, seed, chash = Path(out), int(cfg.scene.integrator.seed), config_hash(cfg)
    ckpt = checkpoint_path(out)
    total, done = _load_checkpoint(ckpt, chash, chunk_spp, seed, n_chunks)
    scene = load_scene(cfg.scene, resolve_device(cfg.get("device", "cpu")))
    out.parent.mkdir(parents=True, exist_ok=True)
    end = n_chunks if stop_after is None else min(n_chunks, done + stop_after)
    with tqdm(total=n_chunks, initial=done, unit="chunk", desc=f"reference {out.name}", disable=not progress) as bar:
        for i in range(done, end):
            image = _render_chunk(scene, cfg, chunk_spp, seed + i)
            total = image if total is None else total + image
            _save_checkpoint(ckpt, total, i + 1, chash, chunk_spp, seed)
            bar.update(1)
    if end < n_chunks:
        return None
    reference = (total / n_chunks).astype(np.float32)
    write_exr(out, reference, {"spp": int(total_spp), "seed": seed, "config_hash": chash})
    ckpt.unlink()
    return reference
