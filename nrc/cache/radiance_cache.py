"""The radiance cache facade: queries with EMA weights, training steps on raw weights, checkpoints.

Build it with :func:`build_radiance_cache` from the three Hydra config blocks:

* ``cache`` (``conf/cache/default.yaml``): network, optimiser, EMA, loss and query settings, see
  :mod:`nrc.cache.settings`.
* ``encoding`` (``conf/encoding/*.yaml``): ``position`` and ``direction`` blocks, each a tiny-cuda-nn
  style encoding config (``otype`` plus its keys, see :mod:`nrc.cache.encodings.factory`); they are
  composed like tcnn's ``Composite``. ``position`` takes any ``otype``; ``direction`` takes
  ``Identity``, ``Frequency``, ``TriangleWave`` (on the unit vector) or ``OneBlob`` (on the spherical
  angles, azimuth wrapped).
* ``extra_inputs`` (``conf/extra_inputs/*.yaml``): booleans ``density``, ``gradient``, ``laplacian``,
  passed to the MLP unencoded (see :mod:`nrc.cache.inputs`).

Units: positions in world units, directions unit vectors (any consistent convention: the cache
stores whatever direction the training targets used), radiance linear RGB float32.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from nrc.cache.allocator import retain_freed_memory
from nrc.config import ConfigReader
from nrc.errors import failure_line
from nrc.cache.ema import WeightEMA
from nrc.cache.encodings.composite import CompositeEncoding
from nrc.cache.encodings.factory import build_encoding
from nrc.cache.encodings.hashgrid import HashGridEncoding
from nrc.cache.encodings.identity import IdentityEncoding
from nrc.cache.encodings.oneblob import OneBlobEncoding
from nrc.cache.inputs import ExtraInputs, InputBuilder
from nrc.cache.loss import relative_l2_luminance
from nrc.cache.network import CacheNetwork
from nrc.cache.optim import build_adam
from nrc.cache.settings import CacheSettings
from nrc.transport.lights import Light
from nrc.volume.grid import DensityGrid

DIRECTION_OTYPES = ("Identity", "Frequency", "TriangleWave", "OneBlob")
MAX_TRAINING_GRAPHS = 4  # training batch sizes with a CUDA graph (RadianceCache.use_graphs); other sizes run eagerly


class _Forward(torch.nn.Module):
    """The network's forward as a module of its own: ``torch.cuda.make_graphed_callables`` replaces the forward of
    the module it is given, and the network's own forward (inference, other batch sizes) must stay as it is."""

    def __init__(self, network: torch.nn.Module) -> None:
        super().__init__()
        self.network = network

    def forward(self, raw: Tensor) -> Tensor:
        return self.network(raw)


class RadianceCache:
    """A trained-online neural radiance cache ``L(x, d)`` for one medium.

    Args:
        inputs: builds raw network inputs (position, direction, extras) from world queries.
        network: encodings + MLP, already on the target device.
        optimizer: Adam over ``network``'s parameters.
        settings: validated cache settings.

    Attributes:
        n_steps: optimiser steps taken.
        n_skipped_steps: training steps skipped because the loss or a gradient was NaN/Inf.
        training_backend: ``"eager"`` or ``"compiled"`` (``settings.compile_training``; a failed compile falls
            back to eager for the rest of the run, its reason in ``training_backend_reason``).
    """

    def __init__(self, inputs: InputBuilder, network: CacheNetwork, optimizer: torch.optim.Optimizer,
                 settings: CacheSettings) -> None:
        self.inputs = inputs
        self.network = network
        self.optimizer = optimizer
        self.settings = settings
        self.ema = WeightEMA(network, settings.ema_alpha, settings.ema_window_fraction, settings.lr_hold,
                             settings.ema_hold_window_fraction)
        self.device = next(network.parameters()).device
        self.n_steps = 0
        self.n_skipped_steps = 0
        self.n_consecutive_skipped = 0  # skipped steps since the last good one
        self.training_backend = "compiled" if settings.compile_training else "eager"
        self.training_backend_reason: str | None = None
        self._compiled_loss = None
        self._graphs: dict[int, Any] | None = None  # batch size -> graphed forward (use_graphs), None: off
        self._make_graphed: Any = None
        self.graphs_reason: str | None = None  # why training graphs stopped (a capture failed), else None

    def use_graphs(self, make_graphed: Any = None) -> None:
        """``renderer.cuda_graphs`` (CUDA): the forward and backward of a training batch replay a CUDA graph
        captured at the first batch of its size (``torch.cuda.make_graphed_callables``; at most
        :data:`MAX_TRAINING_GRAPHS` sizes, others run eagerly). The loss, the NaN/Inf check, Adam and the EMA stay
        eager; the weights are the same tensors, so checkpoints and the EMA see no difference. Not with
        ``compile_training`` (it compiles the same forward) nor ``network.bf16`` (autocast's cast cache). A capture that fails turns the graphs off and says why
        (:attr:`graphs_reason`). ``make_graphed``: the capture function (tests pass a stand-in)."""
        self._graphs = {}
        self._make_graphed = make_graphed if make_graphed is not None else torch.cuda.make_graphed_callables
        if self.training_backend == "compiled":
            self.graphs_reason = "cache.compile_training compiles the training step instead"
        elif self.settings.bf16:  # a captured forward would keep autocast's casts of the weights of its capture
            self.graphs_reason = "cache.network.bf16: autocast's cast cache cannot be captured"

    @property
    def graph_report(self) -> dict[str, Any] | None:
        """The training graphs as they ran (``None``: off): batch sizes captured, and why they stopped if they did."""
        if self._graphs is None:
            return None
        return {"batch_sizes": sorted(self._graphs), "reason": self.graphs_reason}

    def _graphed_forward(self, raw: Tensor) -> Any:
        """The training forward for a batch of ``raw``'s size: its graph (captured now if new), or the network."""
        n = raw.shape[0]
        if n not in self._graphs:
            if len(self._graphs) >= MAX_TRAINING_GRAPHS:
                return self.network
            try:
                self._graphs[n] = self._make_graphed(_Forward(self.network), (raw.detach().clone(),))
            except Exception as exc:  # noqa: BLE001 -- an op that cannot be captured: train without graphs
                self.graphs_reason = (f"capture of a {n}-record training step failed: {type(exc).__name__}: "
                                      f"{failure_line(exc)}")
                warnings.warn(f"nrc: {self.graphs_reason}; training without CUDA graphs", stacklevel=3)
                return self.network
        return self._graphs[n]

    def _loss(self, raw: Tensor, targets: Tensor, net: Any = None) -> Tensor:
        """The loss of one training batch through ``net`` (default: the network)."""
        return relative_l2_luminance((self.network if net is None else net)(raw), targets, self.settings.target_clamp,
                                     self.settings.loss_scale_floor, self.settings.loss_relative_clamp,
                                     self.settings.loss_clamp_to, self.settings.loss_clamp_excess)

    def _training_loss(self, raw: Tensor, targets: Tensor) -> Tensor:
        """The loss of one training batch, through ``torch.compile`` when asked (its backward is compiled with it:
        AOTAutograd). Dynamic batch sizes: one graph serves every batch. A compile that fails falls back to eager
        with a warning (once)."""
        if self.training_backend == "compiled":
            if self._compiled_loss is None:
                self._compiled_loss = torch.compile(self._loss, dynamic=True, fullgraph=True)
            try:
                return self._compiled_loss(raw, targets)
            except Exception as exc:  # a missing C++ compiler or an unsupported op: the eager step still trains
                self.training_backend = "eager"
                self.training_backend_reason = f"torch.compile of the training step failed: {type(exc).__name__}: " \
                    f"{str(exc).splitlines()[0] if str(exc) else ''}"
                warnings.warn(f"nrc: {self.training_backend_reason}; training eagerly", stacklevel=2)
        return self._loss(raw, targets)

    @property
    def mlp_lr(self) -> float:
        """The MLP's learning rate for the next Adam step (``optimizer.lr`` times the schedule's factor)."""
        return self.settings.mlp_adam.lr * self.settings.mlp_lr_factor(self.n_steps)

    @property
    def n_parameters(self) -> int:
        return sum(p.numel() for p in self.network.parameters())

    @property
    def log2_hashmap_size(self) -> int | None:
        """``log2 T`` of the position hash grid's tables (``auto`` resolved), None without a hash grid."""
        sizes = [m.hashmap_size for m in self.network.modules() if isinstance(m, HashGridEncoding)]
        return sizes[0].bit_length() - 1 if sizes else None

    def _raw(self, positions: Tensor, directions: Tensor) -> Tensor:
        if positions.dim() != 2 or positions.shape[1] != 3 or directions.shape != positions.shape:
            raise ValueError(f"positions and directions must both be (N, 3), got {tuple(positions.shape)} "
                             f"and {tuple(directions.shape)}")
        return self.inputs(positions, directions).to(self.device)

    @torch.no_grad()
    def query(self, positions: Tensor, directions: Tensor) -> Tensor:
        """Cached radiance ``(N, 3)`` float32 at world ``positions`` ``(N, 3)`` towards ``directions`` ``(N, 3)``.

        Uses the EMA weights, no autograd, in chunks of ``settings.query_chunk`` points. Predictions
        are not clamped (a linear output can be slightly negative).
        """
        return self._query(self.ema.shadow, positions, directions)

    @torch.no_grad()
    def query_raw(self, positions: Tensor, directions: Tensor) -> Tensor:
        """Like :meth:`query` but with the raw (trained) weights instead of their EMA."""
        return self._query(self.network, positions, directions)

    def _query(self, net: torch.nn.Module, positions: Tensor, directions: Tensor) -> Tensor:
        n = positions.shape[0]
        out = torch.empty(n, 3, dtype=torch.float32, device=self.device)
        chunk = self.settings.query_chunk
        for start in range(0, n, chunk):
            stop = min(start + chunk, n)
            out[start:stop] = net(self._raw(positions[start:stop], directions[start:stop]))
        return out

    def train_step(self, positions: Tensor, directions: Tensor, targets: Tensor) -> float:
        """One Adam step on the raw weights towards radiance ``targets`` ``(N, 3)``; returns the loss.

        An empty batch does nothing and returns 0. If the loss or any gradient is NaN/Inf the step is
        skipped (weights, Adam and EMA state untouched), counted in ``n_skipped_steps``, and the
        non-finite loss is returned.
        """
        if targets.shape != positions.shape:
            raise ValueError(f"targets must be (N, 3) like positions, got {tuple(targets.shape)}")
        if positions.shape[0] == 0:
            return 0.0
        raw = self._raw(positions, directions)
        if self._graphs is not None and self.graphs_reason is None:  # renderer.cuda_graphs: through its graph
            loss = self._loss(raw, targets.to(self.device), self._graphed_forward(raw))
        else:
            loss = self._training_loss(raw, targets.to(self.device))
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        # NaN/Inf anywhere in a gradient makes its sum non-finite (one cheap reduction per tensor; a sum
        # that overflows float32 is treated as non-finite as well).
        sums = [loss.detach()] + [p.grad.sum() for p in self.network.parameters() if p.grad is not None]
        if not bool(torch.isfinite(torch.stack(sums)).all()):
            self.optimizer.zero_grad(set_to_none=True)
            self.n_skipped_steps += 1
            self.n_consecutive_skipped += 1
            return float(loss.detach())
        self.n_consecutive_skipped = 0
        self.optimizer.param_groups[0]["lr"] = self.mlp_lr  # build_adam: the MLP's group first (never lazy)
        self.optimizer.step()
        self.ema.update()
        self.n_steps += 1
        return float(loss.detach())

    def state_dict(self) -> dict[str, Any]:
        """Raw weights, EMA state, Adam state and step counters."""
        return {
            "network": self.network.state_dict(),
            "ema": self.ema.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "n_steps": self.n_steps,
            "n_skipped_steps": self.n_skipped_steps,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state_dict` of a cache built from the same configs."""
        self.network.load_state_dict(state["network"])
        self.ema.load_state_dict(state["ema"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.n_steps = int(state["n_steps"])
        self.n_skipped_steps = int(state["n_skipped_steps"])


def build_radiance_cache(cache_cfg: Any, encoding_cfg: Any, extra_inputs_cfg: Any, grid: DensityGrid,
                         device: torch.device | str, seed: int, training_paths: int | None = None,
                         thick: bool = True, animated: bool = False, lights: Sequence[Light] = ()) -> RadianceCache:
    """Build a :class:`RadianceCache` from the ``cache``, ``encoding`` and ``extra_inputs`` config blocks.

    Args:
        cache_cfg: mapping or DictConfig, keys in :mod:`nrc.cache.settings`.
        encoding_cfg: mapping with ``position`` and ``direction`` encoding blocks.
        extra_inputs_cfg: mapping with booleans ``density``, ``gradient``, ``laplacian``.
        grid: the medium's density grid.
        device: device of the network (cpu or cuda).
        seed: seed of the initial weights (same seed, same weights on every device).
        training_paths: the training paths a frame of the renderer that trains it, for a hash grid's
            ``log2_hashmap_size: auto`` (:func:`nrc.cache.encodings.factory.auto_log2_hashmap_size`); None for a
            cache built on its own (``auto`` is then an error).
        thick: whether the medium is thick (the renderer's ``auto`` regime), for the same and for
            ``loss.clamp_excess: auto``.
        animated: whether the renderer's camera or light moves, for ``optimizer.lr_final_fraction: auto`` and
            ``extra_inputs.light_depth_resolution: auto``.
        lights: the scene's lights, for ``extra_inputs.light_depth`` (none: no light-depth column).

    On CPU this also calls :func:`nrc.cache.allocator.retain_freed_memory` (process-wide glibc malloc
    tuning; without it large temporaries are page-faulted anew on every step).

    Raises:
        nrc.errors.ConfigError: a config value is missing, unknown or out of range (the message names it).
    """
    if torch.device(device).type == "cpu":
        retain_freed_memory()
    settings = CacheSettings.from_config(ConfigReader(cache_cfg, "cache"), animated=animated, thick=thick)
    extras = ExtraInputs.from_config(ConfigReader(extra_inputs_cfg, "extra_inputs"))
    enc_cfg = ConfigReader(encoding_cfg, "encoding")
    pos_cfg, dir_cfg = enc_cfg.block("position"), enc_cfg.block("direction")
    enc_cfg.finish()
    direction_mode = "spherical" if dir_cfg.get_choice("otype", DIRECTION_OTYPES) == "OneBlob" else "vector"
    inputs = InputBuilder(grid, direction_mode, extras, lights, animated)
    (pos_dims, pos_periodic), (dir_dims, dir_periodic) = inputs.column_blocks[:2]
    generator = torch.Generator().manual_seed(int(seed))
    pos_enc, pos_adam = build_encoding(pos_cfg, pos_dims, pos_periodic, generator,
                                       grid_resolution=max(grid.shape), training_paths=training_paths,
                                       thick=thick)
    dir_enc, dir_adam = build_encoding(dir_cfg, dir_dims, dir_periodic, generator, allowed=DIRECTION_OTYPES)
    parts = [(pos_enc, pos_dims), (dir_enc, dir_dims)]
    if extras.n_dims:
        parts.append((IdentityEncoding(extras.n_dims), extras.n_dims))
    if inputs.light_field is not None:  # the light depth: one column, one-blob encoded unless bins 0
        bins = extras.light_depth_bins
        parts.append((OneBlobEncoding(1, bins, (False,)) if bins else IdentityEncoding(1), 1))
    network = CacheNetwork(CompositeEncoding(parts), settings.n_neurons, settings.n_hidden_layers, settings.bf16,
                           generator=generator).to(device)
    groups = [(network.mlp, settings.mlp_adam)]
    groups += [(enc, adam) for enc, adam in ((pos_enc, pos_adam), (dir_enc, dir_adam)) if adam is not None]
    return RadianceCache(inputs, network, build_adam(groups, settings.betas), settings)
