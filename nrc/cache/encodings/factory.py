"""Build an encoding from a tiny-cuda-nn style config block (``{"otype": "HashGrid", ...}``).

Keys per ``otype`` (case-insensitive; unknown keys are errors):

* ``Identity``: none.
* ``Frequency``: ``n_frequencies`` (>= 1).
* ``TriangleWave``: ``n_frequencies`` (>= 1).
* ``OneBlob``: ``n_bins`` (>= 1). Wrap-around is not a key: it is set for the periodic input
  dimensions (the direction's azimuth) by the caller.
* ``HashGrid``: ``n_levels`` (>= 1), ``n_features_per_level`` (>= 1), ``log2_hashmap_size`` (1..24, or
  ``auto``: sized to the NRC renderer's training paths a frame in a thick medium, :func:`auto_log2_hashmap_size`),
  ``base_resolution`` (>= 1), and exactly one of ``per_level_scale`` (>= 1) or ``max_resolution``
  (>= ``base_resolution``; then ``b = (N_max / N_min)^(1 / (L - 1))``), with the finest resolution
  at most 2^20. ``max_resolution: grid`` sizes the finest level to the medium: the density grid's
  largest dimension in voxels, or ``base_resolution`` if that is larger (finer levels cannot resolve
  anything the grid holds); optimiser keys ``lr``
  (default 1e-2), ``eps`` (default 1e-15) and ``lazy`` (default false: a dense Adam update of every entry; true:
  tiny-cuda-nn's, entries no batch touched keep their moments, :class:`nrc.cache.optim.LazyAdam`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from nrc.config import ConfigReader
from nrc.cache.encodings.frequency import FrequencyEncoding
from nrc.cache.encodings.hashgrid import HashGridEncoding
from nrc.cache.encodings.identity import IdentityEncoding
from nrc.cache.encodings.oneblob import OneBlobEncoding
from nrc.cache.encodings.triangle import TriangleWaveEncoding
from nrc.cache.optim import AdamSettings
from nrc.errors import ConfigError

OTYPES = ("Identity", "Frequency", "TriangleWave", "OneBlob", "HashGrid")
MAX_RESOLUTION = 1 << 20
"""Finest hash-grid resolution accepted: beyond it float32 positions cannot resolve the cells."""
ROWS_PER_TRAINING_PATH = 16
"""``log2_hashmap_size: auto`` in a thick medium: table rows per level for each training path a frame (rounded to
a power of two)."""
AUTO_LOG2_RANGE = (14, 19)
"""``log2_hashmap_size: auto`` stays in this range (19: Müller et al. 2021's table, the largest measured here)."""


def auto_log2_hashmap_size(training_paths: int, thick: bool = True) -> int:
    """``log2 T`` for ``training_paths`` training paths a frame: in a thick medium ``log2(ROWS_PER_TRAINING_PATH x
    paths)`` rounded, clamped to :data:`AUTO_LOG2_RANGE`; otherwise the range's top.

    A table learns only what training records reach it, and pays every Adam step for all its entries (Adam, the
    EMA, the gradient's zeroing). At 160x90 (4,608 training paths a frame, ~18k records in 4 steps) a table of 2^16
    rows a level learns the thick cloud as well as 2^19 (NRC+OIDN relMSE after 30 frames, three seeds, -3 % to
    +1 %) at 0.7x the training time; in moderate clouds (median optical depth 7-39) it was 5-12 % worse, so they
    keep 2^19 (docs/measurements/nrc_frames.md, "A hash table sized to the training paths"). 4,096 paths (the default
    ``min_paths``) give 2^16, 40,960 (``max_paths``) 2^19.
    """
    lo, hi = AUTO_LOG2_RANGE
    if not thick:
        return hi
    return min(max(round(math.log2(ROWS_PER_TRAINING_PATH * max(int(training_paths), 1))), lo), hi)


def build_encoding(
    cfg: ConfigReader,
    n_dims: int,
    periodic: Sequence[bool],
    generator: torch.Generator,
    allowed: Sequence[str] = OTYPES,
    grid_resolution: int | None = None,
    training_paths: int | None = None,
    thick: bool = True,
) -> tuple[nn.Module, AdamSettings | None]:
    """Build the encoding described by ``cfg`` for ``n_dims`` inputs.

    Args:
        cfg: the encoding's config block.
        n_dims: number of input columns it encodes.
        periodic: per input column, whether it has period 1 (one-blob wraps those).
        generator: CPU generator for trainable initial values.
        allowed: the ``otype`` values valid at this place.
        grid_resolution: the medium's largest grid dimension, for ``max_resolution: grid``.
        training_paths: the NRC renderer's training paths a frame, for ``log2_hashmap_size: auto``.
        thick: whether the medium is thick (the renderer's ``auto`` regime), for ``log2_hashmap_size: auto``.

    Returns:
        ``(module, adam)``: the encoding (with ``out_dim``) and, for trainable encodings, the Adam
        settings of its parameter group (``None`` otherwise).
    """
    otype = cfg.get_choice("otype", tuple(allowed))
    adam = None
    if otype == "Identity":
        module: nn.Module = IdentityEncoding(n_dims)
    elif otype == "Frequency":
        module = FrequencyEncoding(n_dims, cfg.get_int("n_frequencies", lo=1, hi=24))
    elif otype == "TriangleWave":
        module = TriangleWaveEncoding(n_dims, cfg.get_int("n_frequencies", lo=1, hi=24))
    elif otype == "OneBlob":
        module = OneBlobEncoding(n_dims, cfg.get_int("n_bins", lo=1), wrap=periodic)
    else:
        module, adam = _build_hashgrid(cfg, n_dims, generator, grid_resolution, training_paths, thick)
    cfg.finish()
    return module, adam


def _build_hashgrid(cfg: ConfigReader, n_dims: int, generator: torch.Generator,
                    grid_resolution: int | None, training_paths: int | None,
                    thick: bool) -> tuple[nn.Module, AdamSettings]:
    if n_dims != 3:
        raise ConfigError(f"{cfg.key('otype')}: HashGrid encodes 3-D positions, not {n_dims}-D inputs")
    n_levels = cfg.get_int("n_levels", lo=1)
    n_features = cfg.get_int("n_features_per_level", lo=1)
    log2_t = cfg.get_int_or_auto("log2_hashmap_size", lo=1, hi=24)
    if log2_t is None:
        if training_paths is None:
            raise ConfigError(f"{cfg.key('log2_hashmap_size')}: 'auto' sizes the table to the NRC renderer's training "
                              "paths; give an integer for a cache built on its own")
        log2_t = auto_log2_hashmap_size(training_paths, thick)
    if n_levels << log2_t >= 2**31:
        raise ConfigError(f"{cfg.key('n_levels')} x 2^log2_hashmap_size must be < 2^31 (int32 rows)")
    base = cfg.get_int("base_resolution", lo=1)
    scale = cfg.get_float("per_level_scale", None, lo=1.0)
    if cfg.get_raw("max_resolution") == "grid":
        if grid_resolution is None:
            raise ConfigError(f"{cfg.key('max_resolution')}: 'grid' needs the medium's grid (build the cache for a scene)")
        n_max: int | None = max(grid_resolution, base)  # a grid coarser than N_min: every level at N_min
    else:
        n_max = cfg.get_int("max_resolution", None, lo=base)
    if (scale is None) == (n_max is None):
        raise ConfigError(f"{cfg.key('per_level_scale')}: give exactly one of per_level_scale and max_resolution")
    if scale is None:
        scale = (n_max / base) ** (1.0 / (n_levels - 1)) if n_levels > 1 else 1.0
    if base * scale ** (n_levels - 1) > MAX_RESOLUTION:
        raise ConfigError(f"{cfg.key('per_level_scale')}: the finest resolution N_min b^(L-1) = "
                          f"{base * scale ** (n_levels - 1):.4g} exceeds {MAX_RESOLUTION} (float32 positions)")
    adam = AdamSettings(lr=cfg.get_float("lr", 1e-2, lo=0.0, lo_open=True), eps=cfg.get_float("eps", 1e-15, lo=0.0),
                        lazy=cfg.get_bool("lazy", False))
    return HashGridEncoding(n_levels, n_features, log2_t, base, scale, generator=generator), adam
