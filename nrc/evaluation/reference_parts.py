"""A reference rendered in parts (one per job, on any machines) and merged into the reference EXR.

A reference of ``n`` chunks (:mod:`nrc.evaluation.reference`: chunk ``i`` is a ``chunk_spp`` render with seed
``base + i``) can be split by chunk ranges: :func:`render_part` renders chunks ``[a, b)`` into a **part file**
``<out>.parts/chunks_<a>_<b>.npz`` (float64 sum and sum of squares of its chunks, added in chunk order; the chunks
done; the base seed, ``chunk_spp`` and chunk count; the config and scene hashes; the device and torch version),
rewritten atomically after every chunk, so a killed job, run again with the same range, resumes and writes the same
part. :func:`merge_parts` checks the parts against the config and against each other and writes the reference EXR
(the same header as a one-process reference, noise floor included). It refuses, in one line naming the file: a part
of another scene or another config, another ``chunk_spp``, base seed or chunk count, seeds outside the reference
stream (below ``REF_SEED``), and overlapping chunks; it names the missing chunks (and the ranges to render again).
Parts from different devices or torch versions are merged with a warning (still unbiased; no longer the bits of a
one-process render).

**Equality with one process.** The parts' sums are added in chunk order; a single part covering every chunk is
the one-process sum, bitwise. Several parts add ``(c0 + .. + c3) + (c4 + ..)`` where one process adds chunk after
chunk: float64 rounding (~1e-16 relative), which the float32 image almost never shows (measured in
``docs/running.md``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from tqdm import tqdm

from nrc.config import config_hash, resolve_device, scene_hash
from nrc.errors import ConfigError, NRCError
from nrc.io.atomic import write_atomically
from nrc.evaluation.reference import (REF_SEED, REF_SEEDS_PER_BASE, _chunk_count, chunk_sums, reference_base_seed,
                                      reference_noise_floor, write_reference_exr)
from nrc.render.preview import medium_alpha
from nrc.scene import load_scene

log = logging.getLogger(__name__)
PART_VERSION = 1


class MissingChunks(NRCError):
    """The parts lack chunks the merge needs (every chunk, or enough for the noise-floor target); the message names
    the ranges to render. A job among several merges only when this is not raised."""


def parts_dir(out: str | Path) -> Path:
    """The folder of the parts of the reference ``out``: ``<out>.parts/``."""
    out = Path(out)
    return out.with_name(out.name + ".parts")


def parse_chunks(spec: object, n_chunks: int, key: str = "reference.chunks") -> range:
    """A chunk range: ``all`` (every chunk) or ``"a:b"`` (chunks a..b-1), checked against ``n_chunks``."""
    if spec is None or spec == "all":
        return range(n_chunks)
    text = str(spec)
    try:
        a, b = (int(x) for x in text.split(":"))
    except ValueError:
        raise ConfigError(f"{key} must be 'all' or 'a:b' (chunks a to b - 1), got {spec!r}") from None
    if not 0 <= a < b <= n_chunks:
        raise ConfigError(f"{key}={text}: needs 0 <= a < b <= {n_chunks} (the reference's chunk count)")
    return range(a, b)


def part_path(out: str | Path, chunks: range) -> Path:
    """The part file of ``chunks`` of the reference ``out``."""
    return parts_dir(out) / f"chunks_{chunks.start:05d}_{chunks.stop:05d}.npz"


@dataclass
class Part:
    """A part file read back: its sums, the chunks it holds and what they were rendered with."""

    path: Path
    total: np.ndarray
    total_sq: np.ndarray
    first: int  # the first chunk of its range
    stop: int  # one past the last chunk of its range
    done: int  # chunks done (first .. first + done - 1)
    chunk_spp: int
    base_seed: int
    n_chunks: int
    config_hash: str
    scene_hash: str
    device: str
    torch: str

    @property
    def chunks(self) -> range:
        return range(self.first, self.first + self.done)

    @property
    def complete(self) -> bool:
        return self.first + self.done == self.stop

    @staticmethod
    def read(path: Path) -> Part:
        try:
            with np.load(path, allow_pickle=False) as f:
                d = {k: f[k] for k in f.files}
            if int(d["version"]) != PART_VERSION:
                raise NRCError(f"reference part {path} has format version {int(d['version'])}, not {PART_VERSION}")
            return Part(path, d["sum"], d["sum_sq"], int(d["first"]), int(d["stop"]), int(d["done"]),
                        int(d["chunk_spp"]), int(d["base_seed"]), int(d["n_chunks"]), str(d["config_hash"]),
                        str(d["scene_hash"]), str(d["device"]), str(d["torch"]))
        except (OSError, ValueError, KeyError, EOFError) as exc:
            raise NRCError(f"reference part {path} cannot be read ({type(exc).__name__}: {exc}); delete it and "
                           "render its chunks again") from None

    def write(self) -> None:
        """Atomically (a kill mid-write leaves the previous file)."""
        write_atomically(self.path, lambda f: np.savez(
            f, version=PART_VERSION, sum=self.total, sum_sq=self.total_sq, first=self.first, stop=self.stop,
            done=self.done, chunk_spp=self.chunk_spp, base_seed=self.base_seed, n_chunks=self.n_chunks,
            config_hash=self.config_hash, scene_hash=self.scene_hash, device=self.device, torch=self.torch))


def _plan(cfg: DictConfig, chunk_spp: int, total_spp: int) -> tuple[int, int]:
    """``(chunk count, base seed)`` of a reference, checked."""
    if cfg.renderer.name != "pt":
        raise ConfigError(f"references are rendered with renderer=pt, got renderer={cfg.renderer.name}")
    n_chunks = _chunk_count(chunk_spp, total_spp)
    if n_chunks > REF_SEEDS_PER_BASE:
        raise ConfigError(f"a reference takes at most {REF_SEEDS_PER_BASE} chunks, got {n_chunks}: raise chunk_spp")
    return n_chunks, reference_base_seed(int(cfg.scene.integrator.seed))


def _check(part: Part, chash: str, shash: str, chunk_spp: int, seed: int, n_chunks: int) -> None:
    """Refuse a part that does not belong to this reference (one line naming the file and what differs)."""
    name = part.path
    if part.scene_hash != shash:
        raise NRCError(f"reference part {name} was rendered from another scene (scene hash {part.scene_hash[:12]}, "
                       f"this reference {shash[:12]})")
    if part.config_hash != chash:
        raise NRCError(f"reference part {name} was rendered with another renderer / transmittance config (config "
                       f"hash {part.config_hash[:12]}, this reference {chash[:12]})")
    if part.chunk_spp != chunk_spp:
        raise NRCError(f"reference part {name} has chunk_spp={part.chunk_spp}, this reference {chunk_spp}")
    if part.base_seed < REF_SEED:
        raise NRCError(f"reference part {name} used seeds from {part.base_seed}: below the reference stream "
                       f"({REF_SEED} and up), so not independent of the renders it would judge")
    if part.base_seed != seed:
        raise NRCError(f"reference part {name} has base seed {part.base_seed}, this reference {seed}")
    if part.n_chunks != n_chunks:
        raise NRCError(f"reference part {name} belongs to a reference of {part.n_chunks} chunks, this one has "
                       f"{n_chunks} (another total spp)")


def render_part(cfg: DictConfig, out: str | Path, chunk_spp: int, total_spp: int, chunks: range,
                progress: bool = True, stop_after: int | None = None, floor_target: float | None = None) -> Part:
    """Render (or resume) ``chunks`` of the ``total_spp`` reference of ``cfg`` into their part file (see the
    module docstring); ``stop_after``: at most this many chunks in this call (a kill, for tests);
    ``floor_target``: stop once the part's own noise floor over the medium pixels (:func:`part_floor`) is at most
    this (from 2 chunks on). Returns the part."""
    n_chunks, seed = _plan(cfg, chunk_spp, total_spp)
    if chunks.start < 0 or chunks.stop > n_chunks or len(chunks) == 0:
        raise ConfigError(f"chunks {chunks.start}:{chunks.stop} are outside the reference's 0:{n_chunks}")
    chash, shash = config_hash(cfg), scene_hash(cfg)
    path = part_path(out, chunks)
    device = resolve_device(cfg.get("device", "cpu"))
    if path.is_file():
        part = Part.read(path)
        _check(part, chash, shash, chunk_spp, seed, n_chunks)
    else:
        part = Part(path, np.zeros(0), np.zeros(0), chunks.start, chunks.stop, 0, chunk_spp, seed, n_chunks, chash,
                    shash, device.type, torch.__version__)
    todo = range(chunks.start + part.done, chunks.stop)
    if stop_after is not None:
        todo = todo[:stop_after]
    scene = load_scene(cfg.scene, device) if len(todo) or floor_target is not None else None
    alpha = medium_alpha(scene) if floor_target is not None else None
    if not len(todo) or (floor_target is not None and part_floor(part, alpha) <= floor_target):
        return part
    with tqdm(total=len(chunks), initial=part.done, unit="chunk", desc=f"reference part {path.name}",
              disable=not progress) as bar:
        so_far = (part.total, part.total_sq) if part.done else (None, None)  # a new part's arrays are empty
        for total, total_sq in chunk_sums(scene, cfg, chunk_spp, [seed + i for i in todo], *so_far):
            part.total, part.total_sq = total, total_sq
            part.done += 1
            part.write()
            bar.update(1)
            if floor_target is not None and part_floor(part, alpha) <= floor_target:
                break
    return part


def part_floor(part: Part, alpha: np.ndarray | None) -> float:
    """The noise floor of the chunks a part holds (:func:`target_floor`)."""
    return target_floor(part.total, part.total_sq, part.done, alpha)


def target_floor(total: np.ndarray, total_sq: np.ndarray, n: int, alpha: np.ndarray | None) -> float:
    """The noise floor (``rel_mse_floor``) a ``reference.rel_mse_floor`` target is held against, of ``n`` chunks'
    sums: over the medium pixels (``alpha``), over all pixels where the image shows no medium; infinite below 2
    chunks."""
    if n < 2:
        return math.inf
    floor_all, floor_med = reference_noise_floor(total, total_sq, n, alpha)
    return floor_med if floor_med >= 0 else floor_all


def _ranges(indices: list[int]) -> list[range]:
    """Consecutive runs of sorted chunk indices."""
    runs: list[range] = []
    for i in indices:
        if runs and runs[-1].stop == i:
            runs[-1] = range(runs[-1].start, i + 1)
        else:
            runs.append(range(i, i + 1))
    return runs


def _gather(cfg: DictConfig, out: str | Path, chunk_spp: int, total_spp: int
            ) -> tuple[list[Part], dict[int, Path], int, int, str, str]:
    """The parts of ``<out>.parts/`` checked against the config and each other: ``(parts, chunk -> file, chunk
    count, base seed, config hash, scene hash)``."""
    n_chunks, seed = _plan(cfg, chunk_spp, total_spp)
    chash, shash = config_hash(cfg), scene_hash(cfg)
    folder = parts_dir(out)
    files = sorted(folder.glob("chunks_*.npz")) if folder.is_dir() else []
    if not files:
        raise NRCError(f"no reference parts in {folder}: render them first (reference.chunks=a:b)")
    parts = [Part.read(f) for f in files]
    for part in parts:
        _check(part, chash, shash, chunk_spp, seed, n_chunks)
    parts.sort(key=lambda p: p.first)
    owner: dict[int, Path] = {}
    for part in parts:
        for i in part.chunks:
            if i in owner:
                raise NRCError(f"reference parts {owner[i].name} and {part.path.name} overlap (both hold chunk {i}): "
                               "delete one of them")
            owner[i] = part.path
    kinds = sorted({(p.device, p.torch) for p in parts})
    if len(kinds) > 1:
        log.warning("merging reference parts from different devices / torch versions (%s): unbiased, but not the "
                    "bits one process would render", ", ".join(f"{d} torch {t}" for d, t in kinds))
    return parts, owner, n_chunks, seed, chash, shash


def _sums(parts: list[Part]) -> tuple[np.ndarray, np.ndarray, int, int]:
    """The parts' sums added in chunk order, the number of chunks in them and of parts that hold any."""
    done = [p for p in parts if p.done]
    total, total_sq = done[0].total.copy(), done[0].total_sq.copy()
    for p in done[1:]:
        total += p.total
        total_sq += p.total_sq
    return total, total_sq, sum(p.done for p in done), len(done)


def merge_parts(cfg: DictConfig, out: str | Path, chunk_spp: int, total_spp: int) -> np.ndarray:
    """Merge the parts in ``<out>.parts/`` into the reference EXR ``out`` (the header of
    :func:`~nrc.evaluation.reference.render_reference`, plus ``parts``); returns the (H, W, 3) float32 image.
    Raises :class:`NRCError` naming the part that does not belong, the overlapping parts, or the missing
    chunks."""
    parts, owner, n_chunks, seed, chash, shash = _gather(cfg, out, chunk_spp, total_spp)
    missing = [i for i in range(n_chunks) if i not in owner]
    if missing:
        runs = ", ".join(f"{r.start}:{r.stop}" for r in _ranges(missing))
        raise MissingChunks(f"the reference {Path(out).name} misses {len(missing)} of {n_chunks} chunks; render "
                            f"reference.chunks={runs} (each range as a job), then merge again")
    total, total_sq, n, n_parts = _sums(parts)
    return _write(cfg, out, total, total_sq, n, chunk_spp, seed, chash, shash, n_parts)


def merge_to_floor(cfg: DictConfig, out: str | Path, chunk_spp: int, total_spp: int, target: float,
                   exr_for: Any) -> Path:
    """``reference.rel_mse_floor``: merge every chunk the parts in ``<out>.parts/`` hold (their seeds are
    independent, so any set of them is an unbiased reference of ``chunks x chunk_spp`` spp) into the EXR
    ``exr_for(spp)`` once its noise floor over the medium pixels is at most ``target``; returns its path. Below the
    target it raises :class:`NRCError` naming about how many chunks more it needs (the floor falls as 1 / chunks)
    and the ranges to render, unless every chunk of the ``total_spp`` reference is there: then the reference is
    written with a warning (``scene.integrator.spp`` is the most a floor target renders)."""
    parts, owner, n_chunks, seed, chash, shash = _gather(cfg, out, chunk_spp, total_spp)
    total, total_sq, n, n_parts = _sums(parts)
    alpha = medium_alpha(load_scene(cfg.scene, resolve_device(cfg.get("device", "cpu"))))
    floor = target_floor(total, total_sq, n, alpha)
    if floor > target:
        missing = [i for i in range(n_chunks) if i not in owner]
        need = n_chunks if n < 2 else min(n_chunks, math.ceil(n * floor / target))
        if len(missing) and need > n:
            todo = missing[:need - n]
            runs = ", ".join(f"{r.start}:{r.stop}" for r in _ranges(todo))
            raise MissingChunks(f"the reference {Path(out).name} has {n} chunks, whose noise floor "
                                f"{'(from 2 chunks on)' if n < 2 else f'{floor:.3g}'} is above "
                                f"reference.rel_mse_floor={target:g}: about {need} chunks are needed; render "
                                f"reference.chunks={runs}, then merge again")
        log.warning("the reference's noise floor %.3g is above reference.rel_mse_floor=%g with every chunk of "
                    "scene.integrator.spp=%d: written as it is (raise scene.integrator.spp for more)", floor, target,
                    total_spp)
    path = Path(exr_for(n * chunk_spp))
    _write(cfg, path, total, total_sq, n, chunk_spp, seed, chash, shash, n_parts,
           {"rel_mse_floor_target": float(target)}, alpha)
    return path


def _write(cfg: DictConfig, out: str | Path, total: np.ndarray, total_sq: np.ndarray, n: int, chunk_spp: int,
           seed: int, chash: str, shash: str, n_parts: int, extra: dict | None = None,
           alpha: np.ndarray | None = None) -> np.ndarray:
    """The reference EXR of ``n`` chunks' sums (its header: :func:`~nrc.evaluation.reference.render_reference`'s,
    plus ``parts``); ``alpha``: the scene's medium alpha when the caller has it."""
    reference = (total / n).astype(np.float32)
    if alpha is None:
        alpha = medium_alpha(load_scene(cfg.scene, resolve_device(cfg.get("device", "cpu"))))
    floor_all, floor_med = reference_noise_floor(total, total_sq, n, alpha)
    attrs = {
        "spp": int(n * chunk_spp), "seed": seed, "config_hash": chash, "scene_hash": shash,
        "chunk_spp": int(chunk_spp), "rel_mse_floor": floor_all, "rel_mse_floor_medium": floor_med,
        "alpha": "A channel: 1 - camera-ray transmittance through the medium", "parts": n_parts, **(extra or {}),
    }
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    write_reference_exr(out, reference, alpha, attrs)
    return reference
