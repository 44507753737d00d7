"""Equi-angular distance sampling for point lights (``renderer.point_light_sampling=equiangular``): the pdf over
the non-empty bricks of a segment integrates to one and matches a histogram; the path tracer with it agrees with
next-event estimation at the vertices (and with Mitsuba: tests/test_pt_vs_mitsuba.py)."""

import math

import numpy as np
import pytest
import torch

from conftest import assert_images_agree, compose, hollow_lantern
from nrc.render.registry import make_renderer
from nrc.scene import load_scene
from nrc.transport.equiangular import PhaseAngleTable, sample_distance, segments
from nrc.volume.grid import DensityGrid
from nrc.volume.majorant import MajorantGrid


def _gapped_majorants() -> MajorantGrid:
    """A 16^3 grid in the box [0, 16]^3 with density only in two slabs along x (x-cells 0-4 and 10-14): with
    2-cell bricks the brick of world x in [6.5, 8.5] is empty, a gap that rays along x cross and the pdf skips."""
    d = torch.zeros(16, 16, 16)
    d[0:5] = 1.0
    d[10:15] = 0.5
    grid = DensityGrid(d, center=(8.0, 8.0, 8.0), diagonal=16.0 * math.sqrt(3.0), density_scale=1.0)
    return MajorantGrid(grid, 2)


def test_equiangular_pdf_integrates_to_one_and_matches_a_histogram():
    maj = _gapped_majorants()
    n = 400_000
    o = torch.tensor([[0.0, 8.0, 8.0]]).expand(n, 3).contiguous()
    d = torch.tensor([[1.0, 0.0, 0.0]]).expand(n, 3).contiguous()
    ta, tb = torch.full((n,), 0.0), torch.full((n,), 16.0)
    p = torch.tensor([[7.0, 9.5, 8.0]]).expand(n, 3).contiguous()  # the light beside the gap
    table = PhaseAngleTable(0.7, torch.device("cpu"))  # forward scattering: the pdf follows the phase too
    seg = segments(maj, o, d, ta, tb, p, table)
    t, pdf = sample_distance(seg, torch.rand(n, generator=torch.Generator().manual_seed(2)))
    # integral of the pdf along the segment (fine midpoint rule on one ray)
    m = 64_000
    tt = (torch.arange(m) + 0.5) / m * 16.0
    one = segments(maj, o[:1].expand(m, 3), d[:1].expand(m, 3), ta[:1].expand(m), tb[:1].expand(m), p[:1].expand(m, 3),
                   table)
    dens = one.pdf(tt)
    assert float(dens.sum() * 16.0 / m) == pytest.approx(1.0, abs=2e-3)
    # zero in the empty brick, and no sample there
    assert float(dens[(tt > 6.55) & (tt < 8.45)].max()) == 0.0
    assert float(dens[(tt > 5.0) & (tt < 6.4)].min()) > 0.0
    assert bool(((t <= 6.5 + 1e-4) | (t >= 8.5 - 1e-4)).all())
    # the pdf the sampler returns is the pdf of its samples, and their histogram follows it
    torch.testing.assert_close(pdf, seg.pdf(t))
    hist, edges = np.histogram(t.numpy(), bins=64, range=(0.0, 16.0))
    mid = torch.tensor((edges[:-1] + edges[1:]) / 2, dtype=torch.float32)
    want = segments(maj, o[:64], d[:64], ta[:64], tb[:64], p[:64], table).pdf(mid).numpy() * (16.0 / 64) * n
    full = want > 200  # bins wholly inside a non-empty part (partial bins at brick edges are skipped)
    z = (hist[full] - want[full]) / np.sqrt(want[full])
    assert np.abs(z).max() < 5.0, np.abs(z).max()


def test_phase_angle_table_inverts_its_integral_and_integrates_the_phase():
    """C(pi/2) is the integral of p_HG(-sin theta) d theta (quadrature), inverse(C(theta)) = theta, and the
    density is what C's slope says."""
    from nrc.transport.phase import hg_pdf

    for g in (0.0, 0.5, -0.9):
        table = PhaseAngleTable(g, torch.device("cpu"), n=1024)
        th = torch.linspace(-1.5, 1.5, 301)
        torch.testing.assert_close(table.inverse(table.cdf(th)), th, atol=2e-4, rtol=0)
        q = torch.linspace(-math.pi / 2, math.pi / 2, 200_001, dtype=torch.float64)
        want = float(torch.trapezoid(hg_pdf(g, -torch.sin(q)), q))
        assert float(table.cdf(torch.tensor([math.pi / 2 - 1e-6]))[0]) == pytest.approx(want, rel=1e-3)
        e = 1e-3
        slope = (table.cdf(th + e) - table.cdf(th - e)) / (2 * e)
        torch.testing.assert_close(slope, table.density(th), rtol=0.02, atol=1e-4)


def test_equiangular_segment_that_meets_no_medium_samples_nothing():
    maj = _gapped_majorants()
    o = torch.tensor([[0.0, 8.0, 8.0], [0.0, 8.0, 8.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    seg = segments(maj, o, d, torch.tensor([6.7, 3.0]), torch.tensor([8.3, 3.0]), torch.tensor([[7.0, 9.0, 8.0]] * 2),
                   PhaseAngleTable(0.0, torch.device("cpu")))
    t, pdf = sample_distance(seg, torch.tensor([0.3, 0.7]))
    assert bool((pdf == 0).all()) and bool(torch.isfinite(t).all())


LANTERN = ["renderer=pt", "scene.volume.procedural.resolution=24", "scene.camera.width=16", "scene.camera.height=8",
           "scene.integrator.spp=256", "scene.integrator.max_scatter=6", "scene.volume.density_scale=0.08",
           "scene.volume.g=0.6", "scene.volume.albedo=0.9", "renderer.backend=eager"]


def _renders(extra: list[str], seeds: int = 4) -> list[np.ndarray]:
    out = []
    for seed in range(seeds):
        cfg = compose([*LANTERN, *extra, f"scene.integrator.seed={seed}"])
        out.append(make_renderer("pt", load_scene(cfg.scene), cfg).render().image)
    return out


@pytest.mark.slow
def test_equiangular_agrees_with_next_event_estimation_for_a_light_inside_the_cloud(tmp_path):
    """The lantern in a pocket of clear air inside a thinned cloud (conftest.hollow_lantern): equi-angular
    sampling along segments against next-event estimation at the vertices, block-wise within Monte Carlo error
    over 4 seeds each (dropping the albedo from the equi-angular estimate, 11 % off, fails it by z ~ 14)."""
    scene = hollow_lantern(tmp_path)
    eq = _renders([*scene, "renderer.point_light_sampling=equiangular", "scene.integrator.spp=1024"])
    nee = _renders([*scene, "renderer.point_light_sampling=none", "scene.integrator.spp=4096"])
    assert_images_agree(eq, nee)


def test_equiangular_with_another_light_and_a_transmittance_estimator():
    """A sun beside the lantern (it keeps its next-event estimate) and track-length shadow estimates: the image
    is finite, and it differs from the sun alone by the lantern's light."""
    sun = "{type:directional,direction:[0,-1,0],irradiance:[0.5,0.5,0.5]}"
    extra = ["scene=lantern", "renderer.point_light_sampling=equiangular", "transmittance=track_length",
             "scene.integrator.spp=64"]
    both = _renders([*extra, f"scene.lights=[{{type:point,position:[5,-20,10],intensity:[1200,800,400]}},{sun}]"],
                    seeds=1)[0]
    sun = _renders([*extra, f"scene.lights=[{{type:point,position:[5,-20,10],intensity:[0,0,0]}},{sun}]"], seeds=1)[0]
    assert np.isfinite(both).all()
    assert both.mean() > 1.05 * sun.mean() > 0


def test_clear_pocket_zeroes_the_density_around_a_point_only():
    from nrc.volume.procedural import clear_pocket

    grid = DensityGrid(torch.ones(8, 8, 8), center=(0.0, 0.0, 0.0), diagonal=8.0 * math.sqrt(3.0), density_scale=1.0)
    d = clear_pocket(grid, (0.0, 0.0, 0.0), 1.0)
    assert float(d.sum()) == 512 - 8  # the eight voxels whose centres are sqrt(3)/2 from the centre
    assert float(d[0, 0, 0]) == 1.0 and float(d[3, 4, 3]) == 0.0
