"""``renderer.cuda_graphs``' bookkeeping without a GPU (nrc/render/wavefront/graphs.py): the buckets, the padding with
idle slots, the static buffers, a capture again for another scene and the fallback when a capture fails, with
``call_capture`` (a replay calls the function again on the static inputs and writes the static outputs, as a
replayed graph does). Whole renders through it give the bitwise image of renders without it. The graphs
themselves are checked on a GPU by ``tests/test_cuda.py``."""

import functools

import pytest
import torch

from conftest import compose
from nrc.errors import ConfigError
from nrc.render.registry import make_renderer
from nrc.render.wavefront import graphs as wg
from nrc.render.wavefront import machine as wm
from nrc.render.wavefront.machine import SceneInputs
from nrc.scene import load_scene
from test_pt import make
from test_robustness import TINY as NRC_TINY


def toy(F, I, P, density, majorant):
    """A step of the graphs' contract: each slot's result from its own column, the scene numbers and the tables."""
    n = len(density)
    idx = I[0].clamp(0, n - 1)
    return F * P[0] + density[idx] + majorant[0], I + 1


def inputs(seed=0, n=9):
    g = torch.Generator().manual_seed(seed)
    return SceneInputs(torch.rand(3, generator=g), torch.rand(n, generator=g), torch.rand(4, generator=g))


def state(S, seed):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(5, S, generator=g), torch.randint(0, 9, (2, S), generator=g)


def test_bucket_sizes():
    assert [wg.bucket(n) for n in (1, 2, 63, 64, 65, 128, 129, 1000, 65536)] == \
        [64, 64, 64, 64, 128, 128, 256, 1024, 65536]


def test_step_graphs_equal_direct_calls():
    sg = wg.StepGraphs(5, 2, torch.device("cpu"), capture=wg.call_capture)
    inp = inputs()
    for k, S in enumerate((100, 3, 70, 128, 1, 90)):  # grow and shrink inside and across buckets
        F, I = state(S, k)
        inp.P = inp.P + 0.5  # new scene numbers every call (an animated sun): copied in, no capture
        got = sg.run("track", toy, F, I, inp)
        want = toy(F, I, inp.P, inp.density, inp.majorant)
        assert got[0].shape == (5, S) and torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
    assert sg.captures == 2  # buckets 128 and 64
    g64 = sg._graphs[("track", 64)]
    assert torch.all(g64.F[:, 90:] == 0) and torch.all(g64.I[:, 90:] == 0)  # past the last call's slots: idle
    F, I = state(30, 9)
    a = sg.run("vertex", toy, F, I, inp)  # another function: its own graph
    assert sg.captures == 3 and torch.equal(a[1], I + 1)
    other = inputs(1, n=12)  # another scene's tables: that bucket is captured again
    got = sg.run("track", toy, F, I, other)
    assert sg.captures == 4 and torch.equal(got[0], toy(F, I, other.P, other.density, other.majorant)[0])
    got[0].add_(1.0)  # the caller owns what it gets: the graph's outputs are not touched
    assert torch.equal(sg.run("track", toy, F, I, other)[0], toy(F, I, other.P, other.density, other.majorant)[0])


def refuse(fn, args, pool):
    raise RuntimeError("operation not permitted when stream is capturing\nmore")


def test_a_failed_capture_turns_graphs_off(caplog):
    sg = wg.StepGraphs(5, 2, torch.device("cpu"), capture=refuse)
    F, I = state(10, 0)
    assert sg.run("track", toy, F, I, inputs()) is None  # the caller runs the step itself
    assert not sg.on and sg.reason == ("capture of a 64-slot step failed: RuntimeError: operation not permitted when "
                                       "stream is capturing")
    assert "running the step without graphs" in caplog.text


@pytest.fixture
def cpu_graphs(monkeypatch):
    """Machines built with graphs capture by ``call_capture``, and none is shared with other tests."""
    monkeypatch.setattr(wm, "_machines", [])
    monkeypatch.setattr(wm, "StepGraphs", functools.partial(wg.StepGraphs, capture=wg.call_capture))


def test_path_tracer_through_graphs_is_bitwise_the_same(cpu_graphs):
    over = ["renderer.backend=eager", "renderer.slots=300", "scene.camera.width=24", "scene.camera.height=16",
            "scene.integrator.spp=2"]
    want = make(over)[0].render()
    pt = make(over)[0]
    pt.core.graphs = True
    got = pt.render()
    assert torch.equal(torch.as_tensor(got.image), torch.as_tensor(want.image))
    report = got.metrics["cuda_graphs"]
    assert report["on"] and report["captures"] >= 4  # track and vertex, several buckets (compaction)
    assert want.metrics["cuda_graphs"] is None


def test_a_path_tracer_whose_capture_fails_renders_without_graphs(monkeypatch):
    """The machine runs its own calls once a capture fails (one-slot padding included): the same image, graphs off."""
    monkeypatch.setattr(wm, "_machines", [])
    monkeypatch.setattr(wm, "StepGraphs", functools.partial(wg.StepGraphs, capture=refuse))
    over = ["renderer.backend=eager", "renderer.slots=300", "scene.camera.width=24", "scene.camera.height=16"]
    want = make(over)[0].render()
    pt = make(over)[0]
    pt.core.graphs = True
    got = pt.render()
    assert torch.equal(torch.as_tensor(got.image), torch.as_tensor(want.image))
    assert got.metrics["cuda_graphs"]["on"] is False and got.metrics["cuda_graphs"]["captures"] == 0
    assert got.metrics["cuda_graphs"]["reason"].startswith("capture of a ")


def test_nrc_through_graphs_is_bitwise_the_same(cpu_graphs):
    def run(graphs):
        cfg = compose([*NRC_TINY, "frames=2", "renderer.backend=eager", "renderer.slots=200"])
        r = make_renderer("nrc", load_scene(cfg.scene), cfg)
        for core in r.tracer._cores.values():
            core.graphs = graphs
        return r.render()

    want, got = run(False), run(True)
    assert torch.equal(torch.as_tensor(got.image), torch.as_tensor(want.image))
    assert got.metrics["cuda_graphs"]["captures"] >= 2 and want.metrics["cuda_graphs"] is None


@pytest.mark.parametrize("renderer", ["pt", "nrc"])
def test_cuda_graphs_need_a_gpu(renderer):
    with pytest.raises(ConfigError, match=r"renderer.cuda_graphs=true needs device=cuda \(the scene is on cpu\)"):
        if renderer == "pt":
            make(["renderer.cuda_graphs=true"])
        else:
            cfg = compose([*NRC_TINY, "renderer.cuda_graphs=true"])
            make_renderer("nrc", load_scene(cfg.scene), cfg)
