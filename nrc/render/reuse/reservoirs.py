"""Reservoir reuse of light samples across pixels and frames (ReSTIR) at the render paths' first vertex.

``renderer.reuse.mode`` (``pt`` and ``nrc``): ``none`` | ``spatial`` | ``spatiotemporal``. The render paths'
vertex ``R`` (the first real scattering vertex; the second with deferred reuse, below) does no next-event
estimate in the transport step: the driver records it (:class:`VertexRecord`: position, incoming direction,
throughput x albedo, whether the path goes on and so takes part in the MIS against phase sampling) and after
the wavefront this module makes its estimate of the direct light:

1. **Initial reservoir**: the vertex's own RIS over ``M`` candidates of the source distribution (the
   ``renderer.light_selection`` choice; ``M`` = ``renderer.ris.candidates`` for ``ris``, else 1), weighted
   ``p_hat / p_src`` (:func:`nrc.transport.light_sampling.resample`'s weights); it keeps ``y`` and the
   unbiased contribution weight ``W = sum w / (M p_hat(y))``.
2. **Temporal** (``spatiotemporal``): the vertex is projected into the previous frame's camera (for ``pt``, the
   previous 1-spp pass; the camera does not move) and that pixel's final reservoir of the previous frame is
   combined with the new one, its confidence ``M`` clamped to ``history x M_candidates``.
3. **Spatial**: ``neighbors`` reservoirs of pixels drawn uniformly in a ring of ``1 .. radius`` pixels around
   the pixel (the same sample index for ``spp > 1``) are combined with the pixel's own.
4. **Shading**: the chosen sample's shadow ray is traced *from the receiving vertex* with the configured
   transmittance estimator, and ``beta x f(y) x mis(y) x T x W`` lands in the pixel.

A light sample is ``y = (light index, direction)`` (:meth:`LightSampler.evaluate`): a delta light (sun, point)
is its index, the environment a direction. Its source pdf is the same at every vertex, so a sample keeps its
meaning (and its measure) at another vertex: no Jacobian. The target at vertex ``i`` (position ``x_i``,
incoming direction ``d_i``) is ``p_hat_i(y) = luminance(unshadowed light at x_i) x HG(d_i . wi) x mis_i(y)``,
``mis_i`` the power-heuristic weight of light sampling against phase sampling of the environment (1 for delta
lights; the target follows the MIS-weighted integrand, or the resampling would favour the sky directions in the
phase lobe that phase sampling covers), times the march's transmittance with ``target=coarse`` or ``fine``.

**Unbiased combination** (generalized RIS, Lin et al. 2022): inputs ``i = 0..K`` (0 the receiver) with samples
``y_i``, unbiased contribution weights ``W_i`` and confidences ``M_i`` are resampled with weights
``w_i = m_i(y_i) p_hat_0(y_i) W_i``; the kept ``y`` gets ``W = sum w / p_hat_0(y)`` and ``M = sum M_j``.
``reuse.mis`` chooses the ``m_i``:

- ``balance`` (the default by measurement, ``docs/path_tracer.md``, "Reservoir reuse"): the generalized balance
  heuristic ``M_i p_hat_i(y) / sum_j M_j p_hat_j(y)`` over every input's own target (each evaluated at that
  input's vertex: ``(K+1)^2`` target evaluations).
- ``pairwise`` (Bitterli's pairwise MIS with confidences): the receiver ``c`` against each neighbour ``i``
  alone, ``N = sum_i M_i``: ``m_i(y) = M_i p_hat_i(y) / (N p_hat_i(y) + M_c p_hat_c(y))`` and
  ``m_c(y) = sum_i (M_i / N) M_c p_hat_c(y) / (N p_hat_i(y) + M_c p_hat_c(y))`` (``3K + 1`` evaluations). With
  one neighbour (temporal reuse) it is the balance heuristic.

Both sum to one for every ``y`` the receiver can produce and vanish where input ``i`` cannot produce ``y``, so
the estimate is unbiased for any neighbours; visibility is not in the targets (they are unshadowed and, for
HG with ``|g| < 1``, positive wherever the light is) and is re-traced at the receiver. The MIS weight against
phase sampling of the environment is in the shaded integrand (power heuristic of the source pdf against the
receiver's phase pdf, as the escape side uses), so the two halves still sum to the integral.

**Deferred reuse** (as ReSTIR OG defers to vertices whose sampling distribution is broad): with
``|g| >= defer_g`` the first vertex's phase lobe is so narrow that a neighbour's sample, chosen for another
incoming direction, is nearly worthless there; reuse then starts at vertex 2 (``R = 2``; the first vertex
keeps its own next-event estimate).

**Distance reuse** (``reuse.domain=distance``, :class:`DistanceReuse`): a reservoir holds a pair ``(t, y)``, a
distance along the pixel's camera ray and a light sample, as Lin et al. 2021 resample the camera ray's single
scattering; the steps above are the same (the pair moves to another pixel's ray at the same ``t``), and the
render paths' first vertex leaves all of its direct light to this pass. ``reuse.neighbors=0`` skips spatial
reuse (each pixel's own RIS: the baseline of what reuse adds).

Memory: ``~30`` floats a sample slot (``width x height x spp``) for the record, the reservoirs and the history;
with ``domain=distance`` ``~20 + 2 x distance_steps`` (each ray's extinction table, in the reservoirs and the
history).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, fields, replace
from typing import Any

import torch
from torch import Tensor

from nrc.render.reuse.hook import ReuseHook
from nrc.render.wavefront.program import VertexEvent
from nrc.render.wavefront.setup import camera_rays
from nrc.transport.light_sampling import LightSampler, luminance3, power_heuristic, ris_choice
from nrc.transport.phase import hg_pdf

REUSE_MODES = ("none", "spatial", "spatiotemporal")
REUSE_TARGETS = ("unshadowed", "coarse", "fine")
REUSE_MIS = ("pairwise", "balance")
REUSE_DOMAINS = ("light", "distance")


class CoarseTransmittance:
    """A deterministic approximation of the transmittance for the reuse targets (as Lin et al. 2021 put a
    coarse-grid transmittance into theirs): the density averaged into at most ``cells^3`` cells (nearest cell;
    ``cells <= 0``: the full-resolution grid, trilinear), marched in ``steps`` equal steps
    (:meth:`ExtinctionTable.march`, midpoints). Always positive, so a target that multiplies by it keeps the
    support of the unshadowed one (the estimate stays unbiased); cost ``steps`` lookups a ray.

    Args:
        grid: the :class:`~nrc.volume.grid.DensityGrid`.
        cells: cells per axis at most (``<= 0``: no averaging); steps: march steps.
    """

    def __init__(self, grid: Any, cells: int = 32, steps: int = 16) -> None:
        self.steps = steps
        self.sigma_at = grid.sigma_t
        if cells > 0:
            size = tuple(min(int(n), cells) for n in grid.shape)
            sigma = torch.nn.functional.adaptive_avg_pool3d(grid.density[None, None], size)[0, 0] * grid.density_scale
            self.sigma = sigma.reshape(-1).contiguous()
            self.size = torch.tensor(size, device=grid.device)
            self.lo, self.extent = grid.box.lo, grid.box.hi - grid.box.lo
            self.sigma_at = self._cell_sigma

    def __call__(self, x: Tensor, wi: Tensor, t1: Tensor) -> Tensor:
        """``T`` ``(N,)`` from ``x`` along unit ``wi`` over ``[0, t1]`` (``(N, 3)``, ``(N, 3)``, ``(N,)``)."""
        return torch.exp(-ExtinctionTable.march(self.sigma_at, x, wi, torch.zeros_like(t1), t1, self.steps).total())

    def _cell_sigma(self, p: Tensor) -> Tensor:
        """The averaged extinction of the cells holding points ``p`` ``(..., 3)`` (0 outside the box)."""
        s = (p - self.lo) / self.extent
        inside = ((s >= 0) & (s < 1)).all(-1)
        c = torch.minimum((s.clamp(min=0.0) * self.size).long(), self.size - 1)
        flat = (c[..., 0] * self.size[1] + c[..., 1]) * self.size[2] + c[..., 2]
        return torch.where(inside, self.sigma[flat], torch.zeros_like(p[..., 0]))


@dataclass(frozen=True)
class ReuseSettings:
    """``renderer.reuse`` (``conf/renderer/shared/wavefront.yaml``, included by both renderers; one reader)."""

    mode: str = "none"
    """``none`` | ``spatial`` | ``spatiotemporal`` (module docstring)."""
    neighbors: int = 4
    """Spatial neighbours ``K`` combined per pixel (``>= 0``; the combination costs ``3K + 1`` target
    evaluations with ``mis=pairwise``, ``(K + 1)^2`` with ``balance``). ``0``: no spatial reuse (``spatial``
    is then each pixel's own RIS, the baseline that shows what reuse adds)."""
    radius: float = 10.0
    """Spatial neighbours are drawn uniformly in a ring of 1 to ``radius`` pixels (``>= 1``)."""
    history: float = 20.0
    """Temporal reuse: the previous reservoir's confidence ``M`` is clamped to ``history`` times the initial
    candidates (``> 0``), which bounds how long an old sample can dominate."""
    defer_g: float = 1.0
    """Reuse starts at vertex 2 when ``|g| >= defer_g`` (deferred reuse; ``1``: never, as ``|g| < 1``)."""
    target: str = "unshadowed"
    """The resampling target: ``unshadowed`` (light x phase), ``coarse`` (times :class:`CoarseTransmittance`
    towards the light, the grid averaged into ``32^3`` cells) or ``fine`` (the same march on the full-resolution
    grid: 16 trilinear lookups a target evaluation; with ``domain=distance`` it is the measured best)."""
    mis: str = "balance"
    """The resampling MIS weights of spatial reuse: ``balance`` (the generalized balance heuristic over all
    inputs, ``(K + 1)^2`` target evaluations) or ``pairwise`` (each neighbour against the receiver, ``3K + 1``).
    Temporal reuse (two inputs): the same. ``balance`` is the default by measurement (``docs/path_tracer.md``)."""

    domain: str = "light"
    """What a reservoir holds: ``light`` (a light sample ``y`` for the pixel's own first vertex, which delta
    tracking placed) or ``distance`` (a pair ``(t, y)``: a distance along the pixel's camera ray and a light
    sample, Lin et al. 2021; the camera ray's single scattering of the sampled lights is then estimated by
    the reservoirs alone, see :class:`DistanceReuse`)."""
    distance_candidates: int = 8
    """``domain=distance``: candidate pairs ``(t, y)`` per pixel in the initial RIS (``>= 1``)."""
    distance_steps: int = 32
    """``domain=distance``: equal steps of the extinction table along each camera ray (``>= 1``), read from the
    full-resolution grid at the step midpoints: the distance source and the targets' transmittance. More
    steps resolve a dense cloud's first mean free path (memory: ``steps`` floats a sample slot)."""

    @classmethod
    def from_config(cls, cfg: Any) -> ReuseSettings:
        """Read the ``reuse`` block of a :class:`nrc.config.ConfigReader` of the ``renderer`` block (every key
        required: the defaults live in ``conf/renderer/shared/wavefront.yaml``)."""
        r = cfg.block("reuse")
        settings = cls(mode=r.get_choice("mode", list(REUSE_MODES)),
                       neighbors=r.get_int("neighbors", lo=0),
                       radius=r.get_float("radius", lo=1.0),
                       history=r.get_float("history", lo=0.0, lo_open=True),
                       defer_g=r.get_float("defer_g", lo=0.0, hi=1.0),
                       target=r.get_choice("target", list(REUSE_TARGETS)),
                       mis=r.get_choice("mis", list(REUSE_MIS)),
                       domain=r.get_choice("domain", list(REUSE_DOMAINS)),
                       distance_candidates=r.get_int("distance_candidates", lo=1),
                       distance_steps=r.get_int("distance_steps", lo=1))
        r.finish()
        return settings

    def vertex(self, g: float) -> int:
        """The render paths' vertex whose next-event estimate is reused (0: none)."""
        if self.mode == "none":
            return 0
        if self.domain == "distance":  # the camera ray's single scattering: always the first vertex's
            return 1
        return 2 if abs(float(g)) >= self.defer_g else 1

    @property
    def light_only(self) -> bool:
        """The reuse vertex's direct light is estimated by light sampling alone (``domain=distance``): the path's
        phase-sampled direction from it does not count the environment it reaches (no MIS there)."""
        return self.mode != "none" and self.domain == "distance"

    def hooks(self, g: float) -> tuple:
        """The hooks of the renderers' vertex programs (none without reuse)."""
        vertex = self.vertex(g)
        return (ReuseHook(vertex, self.light_only),) if vertex else ()

    def record(self, n: int, g: float, albedo: float, device: torch.device) -> VertexRecord | None:
        """An empty record of ``n`` sample slots for the reuse vertices (``None``: nothing to record, no reuse or
        ``domain=distance``)."""
        vertex = self.vertex(g)
        return VertexRecord.empty(n, vertex, albedo, device) if vertex and not self.light_only else None

    def metrics(self, g: float) -> dict[str, Any]:
        return {"reuse": self.mode, "reuse_neighbors": self.neighbors if self.mode != "none" else 0,
                "reuse_radius": self.radius, "reuse_history": self.history, "reuse_vertex": self.vertex(g),
                "reuse_target": self.target, "reuse_mis": self.mis, "reuse_domain": self.domain,
                "reuse_distance_candidates": self.distance_candidates if self.domain == "distance" else 0,
                "reuse_distance_steps": self.distance_steps if self.domain == "distance" else 0}


@dataclass
class VertexRecord:
    """The render paths' reuse vertices of one frame (or ``pt`` pass), one row per sample slot
    ``pixel x spp + sample``: position ``x``, incoming unit direction ``d``, throughput x albedo ``beta``
    (``(N, 3)``), ``mis`` (the path goes on from it: the environment's MIS applies) and ``valid`` (``(N,)``).
    A watcher of the wavefront's vertex passes (:meth:`record` of a
    :class:`~nrc.render.wavefront.program.VertexEvent`)."""

    vertex: int
    albedo: float
    x: Tensor
    d: Tensor
    beta: Tensor
    mis: Tensor
    valid: Tensor

    @classmethod
    def empty(cls, n: int, vertex: int, albedo: float, device: torch.device) -> VertexRecord:
        z3 = torch.zeros(n, 3, device=device)
        zb = torch.zeros(n, dtype=torch.bool, device=device)
        return cls(vertex, float(albedo), z3, z3.clone(), z3.clone(), zb, zb.clone())

    @property
    def n(self) -> int:
        return self.x.shape[0]

    def record(self, ev: VertexEvent) -> None:
        """Record the reuse vertices of a vertex pass: render samples at vertex :attr:`vertex` whose direct light
        is estimated there (the renderer's vertex program left that estimate to this pass)."""
        at = (ev.n == self.vertex - 1) & (ev.sample >= 0)
        idx = (at & ev.nee).nonzero().squeeze(1)
        if not len(idx):
            return
        slot = ev.sample[idx]
        mis, scale = ev.mis[idx], ev.scale[idx]
        self.x[slot] = ev.x[idx]
        self.d[slot] = ev.d[idx]
        self.beta[slot] = ev.beta[idx] * self.albedo * scale[:, None]
        self.mis[slot] = mis
        self.valid[slot] = True


class _Rows:
    """Row-wise tensors of a dataclass: ``take`` rows, ``state_dict`` / ``from_state`` for checkpoints."""

    SAMPLE: tuple[str, ...] = ()  # the fields that make up the kept sample (moved by resampling)

    def take(self, idx: Tensor) -> Any:
        return type(self)(*(getattr(self, f.name)[idx] for f in fields(self)))

    def state_dict(self) -> dict[str, Tensor]:
        return {f.name: getattr(self, f.name).cpu() for f in fields(self)}

    @classmethod
    def from_state(cls, state: dict[str, Tensor], device: torch.device) -> Any:
        return cls(**{f.name: state[f.name].to(device) for f in fields(cls)})

    def resampled(self, inputs: list, sel: Tensor, W: Tensor, M: Tensor) -> Any:
        """These receivers with the sample of ``inputs[sel]`` (row-wise), weight ``W`` and confidence ``M``."""
        return replace(self, W=W, M=M, **{k: _gather([getattr(r, k) for r in inputs], sel) for k in self.SAMPLE})


@dataclass
class Reservoirs(_Rows):
    """One reservoir per sample slot: the kept sample ``(light (N,) int64, omega (N, 3))``, its unbiased
    contribution weight ``W`` and confidence ``M`` (``(N,)``), and the vertex it belongs to (``x``, ``d``,
    ``mis``, ``valid``)."""

    light: Tensor
    omega: Tensor
    W: Tensor
    M: Tensor
    x: Tensor
    d: Tensor
    mis: Tensor
    valid: Tensor
    SAMPLE = ("light", "omega")

    @property
    def anchor(self) -> Tensor:
        """The world point temporal reuse projects into the previous camera."""
        return self.x


def _resample(ws: list[Tensor], ps: list[Tensor], u: Tensor, valid: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The end of an initial RIS over ``m = len(ws)`` candidates per row: ``ws`` their resampling weights
    ``p_hat / p_src``, ``ps`` their targets ``p_hat``, ``u`` ``(N,)`` the choice. Returns the chosen index
    ``(N,)``, the contribution weight ``W = sum w / (m p_hat(chosen))`` (0 where the row is invalid or nothing
    has weight) and the confidence ``M = m`` (0 on invalid rows)."""
    m = len(ws)
    sel, total = ris_choice(ws, u)
    ph = _gather(ps, sel)
    ok = valid & (total > 0) & (ph > 0)
    W = torch.where(ok, total / (m * ph).clamp(min=1e-30), torch.zeros_like(total))
    M = torch.where(valid, torch.full_like(total, float(m)), torch.zeros_like(total))
    return sel, W, M


def _gather(values: list[Tensor], sel: Tensor) -> Tensor:
    """``values[sel[n]][n]`` for each row ``n`` (``(N,)`` or ``(N, 3)`` values)."""
    return torch.stack(values, 1)[torch.arange(len(sel), device=sel.device), sel]


class ReservoirReuse:
    """The reuse pass of one renderer (module docstring); keeps the previous frame's reservoirs.

    Args:
        settings: ``renderer.reuse``.
        g: the medium's HG asymmetry.
        spp: sample slots per pixel.
        grid: the density grid (the box for the targets' rays; the ``coarse`` target's density).
    """

    RESERVOIRS: type = Reservoirs
    TARGET_STEPS = 16  # march steps of the coarse / fine target's transmittance towards the light

    def __init__(self, settings: ReuseSettings, g: float, spp: int, grid: Any) -> None:
        self.settings, self.g, self.spp, self.grid = settings, float(g), int(spp), grid
        self.coarse = (CoarseTransmittance(grid, cells=0 if settings.target == "fine" else 32, steps=self.TARGET_STEPS)
                       if settings.target != "unshadowed" else None)
        self.prev: Reservoirs | None = None
        self.prev_camera: Any = None

    # ------------------------------------------------------------------ targets
    def target(self, lights: LightSampler, light: Tensor, omega: Tensor, x: Tensor, d: Tensor,
               mis: Tensor) -> Tensor:
        """``p_hat`` ``(N,)`` of samples ``(light, omega)`` at vertices ``(x, d, mis)``."""
        p, _ = self._target(lights, light, omega, x, d, mis)
        return p

    def _target(self, lights: LightSampler, light: Tensor, omega: Tensor, x: Tensor, d: Tensor,
                mis: Tensor) -> tuple[Tensor, Tensor]:
        """``(p_hat, p_hat / luminance(contribution))``: the target and its factor besides the light (phase x
        MIS x the coarse transmittance)."""
        wi, dist, c, p_src = lights.evaluate(light, omega, x)
        phase = hg_pdf(self.g, (d * wi).sum(-1))
        factor = phase * self._mis(lights, light, p_src, phase, mis)
        if self.coarse is not None:
            factor = factor * self.coarse(x, wi, torch.minimum(self.grid.box.intersect(x, wi)[1], dist))
        return luminance3(c.unbind(1)) * factor, factor

    @staticmethod
    def _mis(lights: LightSampler, light: Tensor, p_src: Tensor, phase: Tensor, mis: Tensor) -> Tensor | float:
        """The light-sampling MIS weight against phase sampling of the environment (1 for the delta lights and
        where the path does not go on): part of the integrand, so part of the target too (without it the
        resampling would favour sky directions in the phase lobe, which phase sampling covers)."""
        if not lights.has_env:
            return 1.0
        env = (light >= lights.env_index) & mis
        return torch.where(env, power_heuristic(p_src, phase), torch.ones_like(phase))

    def initial(self, rec: VertexRecord, lights: LightSampler, gen: torch.Generator) -> Reservoirs:
        """Each recorded vertex's RIS over the sampler's candidates (module docstring, step 1)."""
        n, dev = rec.n, rec.x.device
        m = lights.candidates
        u = torch.rand(n, 4 * m + 1, generator=gen, device=dev)
        ws, ps, ks, om = [], [], [], []
        for j in range(m):
            ls = lights.sample(rec.x, u[:, 4 * j:4 * j + 4])
            p, factor = self._target(lights, ls.light, ls.wi, rec.x, rec.d, rec.mis)
            ws.append(luminance3(ls.weight.unbind(1)) * factor)  # p_hat / p_src, p_src the pdf it was drawn with
            ps.append(p)
            ks.append(ls.light)
            om.append(ls.wi)
        sel, W, M = _resample(ws, ps, u[:, 4 * m], rec.valid)
        return Reservoirs(_gather(ks, sel), _gather(om, sel), W, M, rec.x, rec.d, rec.mis, rec.valid)

    def combine(self, inputs: list[Reservoirs], lights: LightSampler, u: Tensor) -> tuple[Reservoirs, Tensor]:
        """Generalized RIS of ``inputs`` (``inputs[0]`` the receivers) with the MIS weights of ``reuse.mis``
        (module docstring); returns the receivers' new reservoirs and the index of the input each kept."""
        rx = inputs[0]
        Ms = [torch.where(r.valid & rx.valid, r.M, torch.zeros_like(r.M)) for r in inputs]
        p0 = [self.target_at(lights, ri, rx) for ri in inputs]  # p_hat_0(y_i)
        m = self._mis_weights(inputs, Ms, p0, lights)
        ws = [m[i] * p0[i] * ri.W for i, ri in enumerate(inputs)]
        sel, total = ris_choice(ws, u)
        ph = _gather(p0, sel)
        ok = rx.valid & (total > 0) & (ph > 0)
        W = torch.where(ok, total / ph.clamp(min=1e-30), torch.zeros_like(total))
        return rx.resampled(inputs, sel, W, sum(Ms)), sel

    def target_at(self, lights: LightSampler, r: Reservoirs, at: Reservoirs) -> Tensor:
        """``p_hat`` ``(N,)`` at ``at``'s vertices of ``r``'s samples (row-wise)."""
        return self.target(lights, r.light, r.omega, at.x, at.d, at.mis)

    def candidates(self, lights: LightSampler) -> int:
        """The initial RIS's candidates (the unit of the temporal history clamp)."""
        return lights.candidates

    def _mis_weights(self, inputs: list[Reservoirs], Ms: list[Tensor], p0: list[Tensor],
                     lights: LightSampler) -> list[Tensor]:
        """``m_i(y_i)`` per input: the generalized balance heuristic over every input's target (``balance``) or
        the pairwise weights against the receiver (``pairwise``); both sum to one over the inputs for any ``y``
        the receiver can produce and vanish where input ``i``'s target does. With two inputs they coincide."""
        def tgt(r: Reservoirs, at: Reservoirs) -> Tensor:  # p_hat at ``at``'s vertices of r's samples
            return self.target_at(lights, r, at)

        def ratio(a: Tensor, b: Tensor) -> Tensor:
            return torch.where(b > 0, a / b.clamp(min=1e-30), torch.zeros_like(b))

        k = len(inputs)
        if self.settings.mis == "balance" or k == 2:
            ph = [[p0[i] if j == 0 else tgt(ri, inputs[j]) for j in range(k)] for i, ri in enumerate(inputs)]
            return [ratio(Ms[i] * ph[i][i], sum(Ms[j] * ph[i][j] for j in range(k))) for i in range(k)]
        # pairwise: receiver c = 0 against each neighbour i with the neighbours' confidence N = sum M_i:
        # m_i(y) = M_i p_i(y) / (N p_i(y) + M_c p_c(y)),  m_c(y) = sum_i (M_i / N) M_c p_c(y) / (N p_i(y) + M_c p_c(y))
        rx, mc = inputs[0], Ms[0]
        n_nb = sum(Ms[1:])
        at_nb = [tgt(rx, ri) for ri in inputs[1:]]  # p_hat_i(y_0)
        m0 = torch.zeros_like(mc)
        for i, pi in enumerate(at_nb, start=1):
            m0 = m0 + ratio(Ms[i], n_nb) * ratio(mc * p0[0], n_nb * pi + mc * p0[0])
        m0 = torch.where(n_nb > 0, m0, torch.ones_like(m0))
        out = [m0]
        for i, ri in enumerate(inputs[1:], start=1):
            own = tgt(ri, ri)  # p_hat_i(y_i)
            out.append(ratio(Ms[i] * own, n_nb * own + mc * p0[i]))
        return out

    # ------------------------------------------------------------------ reuse
    def temporal(self, cur: Reservoirs, lights: LightSampler, gen: torch.Generator) -> tuple[Reservoirs, Tensor, Tensor]:
        """Combine with the previous frame's reservoir of the pixel the vertex projects to (step 2); returns
        the new reservoirs, the mask of vertices that found a history and the kept input's index."""
        n, dev = len(cur.W), cur.W.device
        pix, inside = self.prev_camera.project(cur.anchor)
        slot = pix * self.spp + torch.arange(n, device=dev) % self.spp
        prev = self.prev.take(slot)
        prev.valid = prev.valid & inside & cur.valid
        prev.M = torch.minimum(prev.M, torch.full_like(prev.M, self.settings.history * self.candidates(lights)))
        out, sel = self.combine([cur, prev], lights, torch.rand(n, generator=gen, device=dev))
        return out, prev.valid, sel

    def neighbours(self, camera: Any, gen: torch.Generator, n: int, device: torch.device) -> list[tuple[Tensor, Tensor]]:
        """``neighbors`` (slot, inside) pairs per sample slot: pixels in the ring ``1 .. radius`` around it."""
        st, W, H = self.settings, camera.width, camera.height
        ids = torch.arange(n, device=device)
        pix, j = torch.div(ids, self.spp, rounding_mode="floor"), ids % self.spp
        col, row = pix % W, torch.div(pix, W, rounding_mode="floor")
        u = torch.rand(st.neighbors, 2, n, generator=gen, device=device)
        out = []
        for k in range(st.neighbors):
            r = torch.sqrt(1.0 + u[k, 0] * (st.radius ** 2 - 1.0))  # uniform in the ring's area
            phi = 2.0 * math.pi * u[k, 1]
            c = col + torch.round(r * torch.cos(phi)).long()
            rr = row + torch.round(r * torch.sin(phi)).long()
            inside = (c >= 0) & (c < W) & (rr >= 0) & (rr < H)
            slot = torch.where(inside, (rr * W + c) * self.spp + j, ids)
            out.append((slot, inside))
        return out

    def spatial(self, cur: Reservoirs, camera: Any, lights: LightSampler,
                gen: torch.Generator) -> tuple[Reservoirs, Tensor]:
        """Combine each reservoir with ``neighbors`` of the same frame (step 3)."""
        n, dev = len(cur.W), cur.W.device
        inputs = [cur]
        for slot, inside in self.neighbours(camera, gen, n, dev):
            r = cur.take(slot)
            r.valid = r.valid & inside
            inputs.append(r)
        return self.combine(inputs, lights, torch.rand(n, generator=gen, device=dev))

    def shade(self, res: Reservoirs, rec: VertexRecord, lights: LightSampler, transmittance: Any, grid: Any,
              majorants: Any, gen: torch.Generator, batch: int) -> Tensor:
        """``beta x f(y) x mis x T x W`` ``(N, 3)`` of each reservoir's sample at its own vertex (step 4)."""
        out = torch.zeros(rec.n, 3, device=rec.x.device)
        idx = (res.valid & (res.W > 0)).nonzero().squeeze(1)
        for a in range(0, len(idx), batch):
            i = idx[a:a + batch]
            x, light = rec.x[i], res.light[i]
            wi, dist, c, p_src = lights.evaluate(light, res.omega[i], x)
            phase = hg_pdf(self.g, (rec.d[i] * wi).sum(-1))
            w = phase * res.W[i] * self._mis(lights, light, p_src, phase, rec.mis[i])
            t1 = torch.minimum(grid.box.intersect(x, wi)[1], dist)
            T = transmittance(grid, majorants, x, wi, torch.zeros_like(t1), t1, gen)
            out[i] = rec.beta[i] * c * (w * T)[:, None]
        return out

    def frame(self, rec: VertexRecord | None, camera: Any, lights: LightSampler, transmittance: Any, grid: Any,
              majorants: Any, gen: torch.Generator, batch: int) -> tuple[Tensor, dict[str, Any]]:
        """The reuse pass of a frame: ``(contribution (N, 3) per sample slot, counters)``; with
        ``spatiotemporal`` the frame's final reservoirs become the next frame's history. ``rec``: the recorded
        vertices (``domain=light``; :class:`DistanceReuse` draws its own camera rays through ``camera`` and
        takes none)."""
        t0 = time.perf_counter()
        mode = self.settings.mode
        if lights.n_lights == 0:  # nothing to sample (every light equi-angular, or none)
            n = rec.n if rec is not None else camera.num_pixels * self.spp
            valid = int(rec.valid.sum()) if rec is not None else 0
            return torch.zeros(n, 3, device=grid.device), {"reuse_vertices": valid,
                                                           "time_reuse_s": time.perf_counter() - t0}
        cur = self.frame_initial(rec, camera, lights, gen)
        valid = cur.valid
        n_valid = max(int(valid.sum()), 1)
        stats: dict[str, Any] = {"reuse_vertices": int(valid.sum())}
        if mode == "spatiotemporal" and self.prev is not None and len(self.prev.W) == len(cur.W):
            cur, hist, sel = self.temporal(cur, lights, gen)
            stats["reuse_temporal_found"] = int(hist.sum()) / n_valid
            stats["reuse_temporal_accept"] = int((hist & (sel == 1)).sum()) / n_valid
        if self.settings.neighbors:
            cur, sel = self.spatial(cur, camera, lights, gen)
            stats["reuse_spatial_accept"] = int((valid & (sel > 0)).sum()) / n_valid
        stats["reuse_mean_m"] = float(cur.M[valid].mean()) if bool(valid.any()) else 0.0
        if mode == "spatiotemporal":
            self.prev, self.prev_camera = cur, camera
        out = self.shade(cur, rec, lights, transmittance, grid, majorants, gen, batch)
        stats["time_reuse_s"] = time.perf_counter() - t0
        return out, stats

    def frame_initial(self, rec: VertexRecord | None, camera: Any, lights: LightSampler,
                      gen: torch.Generator) -> Reservoirs:
        """The frame's initial reservoirs, one per sample slot (the light domain: :meth:`initial` at the
        recorded vertices; the distance domain: on the camera rays)."""
        return self.initial(rec, lights, gen)

    def state_dict(self) -> dict[str, Any] | None:
        """The history (``None`` without one) for a checkpoint; the caller restores ``prev_camera``."""
        return None if self.prev is None else self.prev.state_dict()

    def load_state_dict(self, state: dict[str, Any] | None, camera: Any, device: torch.device) -> None:
        self.prev = None if state is None else self.RESERVOIRS.from_state(state, device)
        self.prev_camera = camera if state is not None else None


class _Table:
    """Per-ray extinction tables: rays ``o``, ``d`` ``(N, 3)`` with a span ``[ta, tb]`` ``(N,)``, the extinction
    read at the midpoints of ``S`` equal steps over it, kept as its optical depth at each step's end ``cum``
    ``(N, S)`` (a prefix sum, built once a ray; the step's extinction is its difference), and ``valid`` ``(N,)``
    (the span is not empty). Piecewise constant: a deterministic control for the distance source, the targets
    and the residual transmittance estimate. Memory: ``S`` floats a ray."""

    def tau(self, t: Tensor, rows: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Along these rays (or the ``rows`` of them) at distances ``t`` ``(N,)``: the table's optical depth from
        ``ta``, its extinction there, and whether ``t`` lies in ``[ta, tb]`` of a valid ray."""
        rows = torch.arange(len(t), device=t.device) if rows is None else rows
        S = self.cum.shape[1]
        ta, tb = self.ta[rows], self.tb[rows]
        h = (tb - ta).clamp(min=1e-30) / S
        k = torch.floor((t - ta) / h).clamp(0, S - 1).long()
        sig_k = self.step_sigma(rows, k, h)
        tau = self.cum[rows, k] - sig_k * ((k + 1).to(t.dtype) * h - (t - ta))
        inside = self.valid[rows] & (t >= ta) & (t <= tb)
        return tau, sig_k, inside

    def step_sigma(self, rows: Tensor, k: Tensor, h: Tensor) -> Tensor:
        """The table's extinction in step ``k`` of ``rows`` (step length ``h``), from the prefix sum."""
        before = torch.where(k > 0, self.cum[rows, (k - 1).clamp(min=0)], torch.zeros_like(h))
        return (self.cum[rows, k] - before) / h

    def total(self) -> Tensor:
        """The table's optical depth of the whole span ``(N,)``."""
        return self.cum[:, -1]

    def transmittance(self, grid: Any, t: Tensor, points: float, gen: torch.Generator) -> Tensor:
        """An unbiased estimate of ``T(ta, t)`` ``(N,)`` on these rays: residual ratio tracking with the table as
        the control, ``exp(-tau_table(t)) prod_i (1 - (sigma_t(x_i) - sig(x_i)) / mu)`` over a Poisson process
        of rate ``mu`` on ``[ta, t]`` (``E prod = exp(-int (sigma_t - sig))`` for any rate, so no bound is
        needed; the relative second moment is ``exp(int (sigma_t - sig)^2 / mu)``, small where the table
        resolves the grid). ``mu = max(points / (t - ta), the table's largest jump between steps)``, at most
        ``4 points / (t - ta)``: ``points`` density lookups a ray on average where the table is fine, up to
        ``4 points`` where it is coarse against the grid (which keeps the factors near ``[0, 2]`` there). Not
        bounded to ``[0, 1]``."""
        tau, _, _ = self.tau(t)
        span = (t - self.ta).clamp(min=0.0)
        S = self.cum.shape[1]
        sig = torch.diff(self.cum, dim=1, prepend=torch.zeros_like(self.cum[:, :1])) * (S / (self.tb - self.ta)
                                                                                          .clamp(min=1e-30))[:, None]
        jump = (sig[:, 1:] - sig[:, :-1]).abs().amax(1) if S > 1 else torch.zeros_like(span)
        base = float(points) / span.clamp(min=1e-30)
        mu = torch.maximum(base, torch.minimum(jump, 4.0 * base))  # about the residual's size, within 4x
        n = torch.poisson(mu * span, generator=gen).long()
        k = int(n.max().item()) if len(n) else 0
        u = torch.rand(len(n), k, generator=gen, device=t.device)
        i, j = (torch.arange(k, device=t.device)[None, :] < n[:, None]).nonzero(as_tuple=True)
        ti = self.ta[i] + u[i, j] * span[i]
        resid = grid.sigma_t(self.o[i] + ti[:, None] * self.d[i]) - self.tau(ti, i)[1]
        factor = torch.ones(len(n), max(k, 1), device=t.device)
        factor[i, j] = 1.0 - resid / mu[i]
        return torch.exp(-tau) * factor.prod(1)


@dataclass
class ExtinctionTable(_Table, _Rows):
    """A :class:`_Table` with its rays (shadow segments; the camera rays of :class:`DistanceReservoirs`)."""

    o: Tensor
    d: Tensor
    ta: Tensor
    tb: Tensor
    cum: Tensor
    valid: Tensor

    @classmethod
    def march(cls, sigma: Any, o: Tensor, d: Tensor, ta: Tensor, tb: Tensor, steps: int) -> ExtinctionTable:
        """The table of ``steps`` equal steps over ``[ta, tb]`` ``(N,)`` of rays ``o``, ``d``: the extinction
        ``sigma(points (M, 3)) -> (M,)`` (the grid's ``sigma_t``, or :class:`CoarseTransmittance`'s cells) read
        at the steps' midpoints, ``steps`` lookups a ray with a non-empty span."""
        valid = tb > ta
        i = valid.nonzero().squeeze(1)  # empty spans read nothing (their table is 0)
        frac = (torch.arange(steps, device=o.device, dtype=o.dtype) + 0.5) / steps
        tm = ta[i, None] + frac[None, :] * (tb - ta)[i, None]
        sig = sigma((o[i, None, :] + tm[..., None] * d[i, None, :]).reshape(-1, 3)).view(len(i), steps)
        cum = torch.zeros(len(o), steps, device=o.device, dtype=o.dtype)
        cum[i] = torch.cumsum(sig, 1) * ((tb - ta)[i] / steps)[:, None]
        return cls(o, d, ta, tb, cum, valid)


@dataclass
class DistanceReservoirs(ExtinctionTable):
    """``domain=distance``: one reservoir per sample slot holding a pair ``(t, y)``: the distance ``t`` ``(N,)``
    along the slot's camera ray and the light sample ``(light, omega)``; ``W``, ``M`` as :class:`Reservoirs`;
    the camera ray (``o``, ``d`` ``(N, 3)``; ``ta``, ``tb`` ``(N,)`` its span in the box) and its extinction
    table (:class:`_Table`, ``cum`` ``(N, S)``, ``S = distance_steps``: the distance source, the targets'
    transmittance and the camera segment's control); ``valid``: the ray crosses the box."""

    t: Tensor
    light: Tensor
    omega: Tensor
    W: Tensor
    M: Tensor
    SAMPLE = ("t", "light", "omega")

    @property
    def anchor(self) -> Tensor:
        """The kept sample's point: temporal reuse finds the previous frame's pixel through it."""
        return self.o + self.t[:, None] * self.d


class DistanceReuse(ReservoirReuse):
    """Reuse of ``(distance, light)`` pairs on the camera rays (``renderer.reuse.domain=distance``; Lin, Wyman
    and Yuksel 2021, with the generalized RIS of the module docstring).

    The pixel's single scattering of the sampled lights, ``I = int_ta^tb T(ta, t) sigma_s(x_t) int
    p(d, wi) L(x_t, wi) T(x_t -> y) dy dt`` along its camera ray ``x_t = o + t d``, is estimated by this pass
    alone; the render path's first vertex does no next-event estimate of those lights and its phase-sampled
    direction does not count the environment it reaches (:attr:`ReuseSettings.light_only`; the camera ray's
    escape and the rest of the path stay the path's). The direct light of the first vertex is thus resampled
    over where the vertex is, not only over which light: reuse spreads good distances across pixels, which the
    ``light`` domain cannot.

    - **Samples.** ``z = (t, y)``; a pair shifts to another pixel's camera ray at the same ``t`` (the measure
      ``dt x dy`` is the same on every ray: no Jacobian), the light sample as in the ``light`` domain.
    - **Source.** ``t`` from the extinction table ``sig`` along the ray (the grid read at the midpoints of
      ``distance_steps`` equal steps; pdf ``sig(t) exp(-tau(t)) / (1 - exp(-tau_total))``) mixed
      with a uniform share :attr:`UNIFORM` over ``[ta, tb]`` (positive wherever the medium can be), then one
      light sample at ``x_t`` from ``renderer.light_selection``; ``distance_candidates`` such pairs.
    - **Target.** ``p_hat(t, y) = sigma_s(x_t) exp(-tau(t)) luminance(L) HG`` (times the coarse
      transmittance towards the light with ``target=coarse``): the integrand without the two visibilities.
      No MIS against phase sampling (the light sampling covers the whole of ``I``).
    - **Shading.** ``sigma_s(x_t) T(ta, t) HG L T(x_t -> y) W``, added to the slot. Both transmittances are
      residual ratio tracking against an extinction table (:meth:`_Table.transmittance`; unbiased): the camera
      segment against the ray's own table (:attr:`CAMERA_POINTS` residual lookups), the shadow segment against
      a :attr:`LIGHT_STEPS`-step table marched for it (:attr:`LIGHT_POINTS`). Not the configured
      ``transmittance`` estimator: on the side-lit Disney cloud the table-controlled camera estimate has a tenth
      of ratio tracking's variance at a tenth of its time, and the shading's weight ``f / p_hat`` carries that
      variance straight into the pixel.

    Needs ``cache_target=indirect`` under ``nrc`` (with ``full`` a path terminating at its first vertex would
    count that vertex's direct light in the cache's answer too).
    """

    RESERVOIRS = DistanceReservoirs
    UNIFORM = 0.25
    CAMERA_POINTS = 8  # density lookups a camera segment's transmittance takes on average (table control)
    LIGHT_STEPS = 64  # the shadow segment's control table
    LIGHT_POINTS = 8  # and its residual lookups on average

    def __init__(self, settings: ReuseSettings, g: float, spp: int, grid: Any, albedo: float) -> None:
        super().__init__(settings, g, spp, grid)
        self.albedo = float(albedo)

    def candidates(self, lights: LightSampler) -> int:
        return self.settings.distance_candidates

    # ------------------------------------------------------------------ rays, distances, targets
    def rays(self, camera: Any, n: int, gen: torch.Generator) -> DistanceReservoirs:
        """Empty reservoirs on ``n`` jittered camera rays (slot ``pixel x spp + j``) with their coarse tables."""
        dev = self.grid.device
        ids = torch.arange(n, device=dev)
        pix = torch.div(ids, self.spp, rounding_mode="floor")
        o, d, ta, tb = camera_rays(camera, self.grid, pix, torch.rand(n, 2, generator=gen, device=dev))
        o, d = o.contiguous(), d.contiguous()
        ta = ta.clamp(min=0.0)
        valid = tb > ta
        tb = torch.where(valid, tb, ta)
        tab = ExtinctionTable.march(self.grid.sigma_t, o, d, ta, tb, self.settings.distance_steps)
        z = torch.zeros(n, device=dev)
        return DistanceReservoirs(o, d, ta, tb, tab.cum, valid, t=z, W=z.clone(), M=z.clone(),
                                  light=torch.zeros(n, dtype=torch.long, device=dev),
                                  omega=torch.zeros(n, 3, device=dev))

    def _mix(self, r: DistanceReservoirs) -> Tensor:
        """The exponential share of the distance source (none on a ray whose table depth is 0)."""
        return torch.where(r.total() > 1e-6, torch.full_like(r.ta, 1.0 - self.UNIFORM), torch.zeros_like(r.ta))

    def distance_pdf(self, r: DistanceReservoirs, t: Tensor) -> Tensor:
        """The source pdf ``(N,)`` of distances ``t`` on rays ``r`` (0 outside ``[ta, tb]``)."""
        tau, sig_k, inside = r.tau(t)
        a = self._mix(r)
        norm = (-torch.expm1(-r.total())).clamp(min=1e-30)
        p = a * sig_k * torch.exp(-tau) / norm + (1.0 - a) / (r.tb - r.ta).clamp(min=1e-30)
        return torch.where(inside, p, torch.zeros_like(p))

    def sample_distance(self, r: DistanceReservoirs, u0: Tensor, u1: Tensor) -> Tensor:
        """Distances ``(N,)`` on rays ``r`` from the source (``u0`` picks the part, ``u1`` inverts it)."""
        S = r.cum.shape[1]
        span = r.tb - r.ta
        h = span / S
        uniform = r.ta + u1 * span
        target = -torch.log1p(-u1 * (-torch.expm1(-r.total())))  # optical depth of the exponential part
        k = torch.searchsorted(r.cum.contiguous(), target[:, None].contiguous(), right=True)[:, 0].clamp(max=S - 1)
        rows = torch.arange(len(u0), device=u0.device)
        sig_k = r.step_sigma(rows, k, h)
        into = (target - (r.cum[rows, k] - sig_k * h)) / sig_k.clamp(min=1e-30)
        expo = r.ta + k.to(u1.dtype) * h + into.clamp(min=0.0).minimum(h)
        return torch.where(u0 < self._mix(r), expo, uniform).clamp(min=r.ta, max=r.tb)

    def _dtarget(self, lights: LightSampler, t: Tensor, light: Tensor, omega: Tensor,
                 at: DistanceReservoirs) -> tuple[Tensor, Tensor]:
        """``(p_hat, p_hat / luminance(L))`` of samples ``(t, light, omega)`` on ``at``'s rays."""
        tau, _, inside = at.tau(t)
        x = at.o + t[:, None] * at.d
        wi, dist, c, _ = lights.evaluate(light, omega, x)
        factor = self.albedo * self.grid.sigma_t(x) * torch.exp(-tau) * hg_pdf(self.g, (at.d * wi).sum(-1))
        if self.coarse is not None:
            factor = factor * self.coarse(x, wi, torch.minimum(self.grid.box.intersect(x, wi)[1], dist))
        factor = torch.where(inside, factor, torch.zeros_like(factor))
        return luminance3(c.unbind(1)) * factor, factor

    def target_at(self, lights: LightSampler, r: Any, at: Any) -> Tensor:
        return self._dtarget(lights, r.t, r.light, r.omega, at)[0]

    # ------------------------------------------------------------------ the pass
    def frame_initial(self, rec: Any, camera: Any, lights: LightSampler, gen: torch.Generator) -> DistanceReservoirs:
        return self.initial(camera, camera.num_pixels * self.spp, lights, gen)

    def initial(self, camera: Any, n: int, lights: LightSampler, gen: torch.Generator) -> DistanceReservoirs:
        """Each camera ray's RIS over ``distance_candidates`` pairs ``(t, y)`` (class docstring)."""
        r = self.rays(camera, n, gen)
        m = self.settings.distance_candidates
        u = torch.rand(n, 6 * m + 1, generator=gen, device=r.o.device)
        ws, ps, ts, ks, om = [], [], [], [], []
        for j in range(m):
            t = self.sample_distance(r, u[:, 6 * j], u[:, 6 * j + 1])
            ls = lights.sample(r.o + t[:, None] * r.d, u[:, 6 * j + 2:6 * j + 6])
            p, factor = self._dtarget(lights, t, ls.light, ls.wi, r)
            pt = self.distance_pdf(r, t)
            w = luminance3(ls.weight.unbind(1)) * factor / pt.clamp(min=1e-30)  # p_hat / (p_t p_src)
            ws.append(torch.where(pt > 0, w, torch.zeros_like(w)))
            ps.append(p)
            ts.append(t)
            ks.append(ls.light)
            om.append(ls.wi)
        sel, W, M = _resample(ws, ps, u[:, 6 * m], r.valid)
        return replace(r, t=_gather(ts, sel), light=_gather(ks, sel), omega=_gather(om, sel), W=W, M=M)

    def shade(self, res: Any, rec: Any, lights: LightSampler, transmittance: Any, grid: Any,
              majorants: Any, gen: torch.Generator, batch: int) -> Tensor:
        """``sigma_s T(ta, t) HG L T(x_t -> y) W`` ``(N, 3)`` of each reservoir's pair on its own camera ray."""
        out = torch.zeros(len(res.W), 3, device=res.o.device)
        idx = (res.valid & (res.W > 0)).nonzero().squeeze(1)
        for a in range(0, len(idx), batch):
            i = idx[a:a + batch]
            r = res.take(i)
            x = r.o + r.t[:, None] * r.d
            wi, dist, c, _ = lights.evaluate(r.light, r.omega, x)
            w = self.albedo * grid.sigma_t(x) * hg_pdf(self.g, (r.d * wi).sum(-1)) * r.W
            t_cam = r.transmittance(grid, r.t, self.CAMERA_POINTS, gen)
            t1 = torch.minimum(grid.box.intersect(x, wi)[1], dist)
            shadow = ExtinctionTable.march(grid.sigma_t, x, wi, torch.zeros_like(t1), t1, self.LIGHT_STEPS)
            t_light = shadow.transmittance(grid, t1, self.LIGHT_POINTS, gen)
            out[i] = c * (w * t_cam * t_light)[:, None]
        return out


def make_reuse(settings: ReuseSettings, g: float, spp: int, grid: Any, albedo: float) -> ReservoirReuse | None:
    """The reuse pass ``renderer.reuse`` asks for (``None`` for ``mode=none``)."""
    if settings.mode == "none":
        return None
    if settings.domain == "distance":
        return DistanceReuse(settings, g, spp, grid, albedo)
    return ReservoirReuse(settings, g, spp, grid)
