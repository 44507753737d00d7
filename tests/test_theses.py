"""The theses' experiments (``scripts/theses.py``): the configs compose with every variant, the registry covers
THESES.md, the verdicts decide on synthetic numbers, the pages build from a synthetic result."""

from __future__ import annotations

import json
import re

import pytest

from conftest import CONF_DIR, REPO, load_script

th = load_script("theses")
THESES_MD = REPO.parent / "shared" / "THESES.md"
THESIS_CONFIGS = sorted(p.stem for p in (CONF_DIR / "experiment").glob("thesis_*.yaml"))


def test_thesis_configs_exist_and_set_the_theses_values():
    from nrc.config import compose

    assert THESIS_CONFIGS == ["thesis_fedotov", "thesis_spindler"]
    s = compose(["+experiment=thesis_spindler"])
    assert (s.cache.network.n_neurons, s.cache.network.n_hidden_layers) == (64, 6)
    assert s.encoding.position.n_levels == 12 and s.encoding.direction.n_bins == 4
    assert s.cache.optimizer.lr == s.encoding.position.lr == 0.01 and s.cache.ema.alpha == 0.99
    # Mueller's relative L2 at a constant rate (S:535, S:710), not our floor, clamp and decay
    assert (s.cache.loss.scale_floor, s.cache.loss.relative_clamp, s.cache.optimizer.lr_final_fraction) == (0, 0, 1)
    assert (s.renderer.termination.min_vertices, s.renderer.termination.p_continue) == (1, 0.5)
    assert (s.scene.volume.density_scale, s.scene.volume.albedo, s.scene.volume.g) == (0.6, 1.0, 0.8)
    assert s.scene.integrator.max_scatter == 32 and s.transmittance.name == "ratio"
    assert [light.type for light in s.scene.lights] == ["directional"]
    f = compose(["+experiment=thesis_fedotov"])
    assert f.batch_filter.name == "quadtree" and f.batch_filter.depth == 1 and f.extra_inputs.density


def test_every_config_line_cites_or_says_not_stated():
    """Each setting of a thesis config carries a comment (a thesis line, or why the value was chosen)."""
    for name in THESIS_CONFIGS:
        for line in (CONF_DIR / "experiment" / f"{name}.yaml").read_text().splitlines():
            if re.match(r"^\s+\w+: [^{]", line) and not line.strip().startswith("#"):
                assert "#" in line, f"{name}: {line.strip()!r} has no comment"


@pytest.fixture(scope="module")
def grid():
    import torch

    from nrc.volume.grid import DensityGrid

    return DensityGrid(torch.rand(8, 8, 8), [0.0, 0.0, 0.0], 10.0, 1.0)


def builds(cfg, grid) -> None:
    """The cache and the batch filter of ``cfg`` build (their readers refuse unknown keys)."""
    from nrc.cache import build_radiance_cache
    from nrc.render.radiance_caching.batch_filter import make_batch_filter

    build_radiance_cache(cfg.cache, cfg.encoding, cfg.extra_inputs, grid, "cpu", 0, training_paths=1024)
    make_batch_filter(cfg.batch_filter)


@pytest.mark.parametrize("exp", th.EXPERIMENTS, ids=lambda e: e.id)
def test_every_variant_composes_and_builds(exp, grid):
    from nrc.config import compose

    scale = th.Scale()
    for name, variant in exp.variants.items():
        cfg = compose(scale.overrides(exp, variant))
        assert cfg.renderer.name == "nrc", name
        builds(cfg, grid)
    extra: list[str] = []
    for _, ovs in exp.explain:  # the ladder's steps compose; all of them together on every variant, and build
        extra += ovs
        compose(scale.overrides(exp, [*next(iter(exp.variants.values())), *extra]))
    if exp.explain:
        for variant in exp.variants.values():
            builds(compose(scale.overrides(exp, [*variant, *extra])), grid)


def test_variants_are_what_they_say():
    """A variant's group choice is not undone by the thesis config's own keys."""
    from nrc.config import compose

    scale = th.Scale()

    def cfg(exp_id: str, variant: str):
        exp = th.BY_ID[exp_id]
        return compose(scale.overrides(exp, exp.variants[variant]))

    assert not cfg("F-6.1b", "none").extra_inputs.density and cfg("F-6.1b", "density").extra_inputs.density
    g = cfg("F-6.1a", "gradient").extra_inputs
    assert g.gradient and not g.density and not g.laplacian
    assert cfg("F-6.2", "stripes/a").batch_filter.n_stripes == 4 and cfg("F-6.2", "none/a").batch_filter.n_batches == 4
    assert cfg("F-6.2", "quadtree/a").batch_filter.depth == 1
    assert cfg("S-5.3.2", "T12/3x64").encoding.position.otype == "TriangleWave"
    assert cfg("S-5.3.2", "T12/3x64").cache.network.n_hidden_layers == 3
    assert cfg("S-5.3.3-Ex2", "scene 0, density 0.25").scene.volume.density_scale == 0.25
    (light,) = cfg("S-5.3.3-Ex3", "scene 1, density 0.6").scene.lights
    assert light.type == "point" and list(light.position) == [0.0, 0.0, 0.0]
    assert cfg("S-5.3.1", "no EMA").cache.ema.alpha == 0.0


def test_registry_covers_theses_md():
    ids = {e.id for e in th.EXPERIMENTS}
    assert len(ids) == len(th.EXPERIMENTS)
    assert sorted(e.number for e in th.EXPERIMENTS) == list(range(1, 18))
    assert all(e.kind in th.MEASURE and e.config in THESIS_CONFIGS for e in th.EXPERIMENTS)
    if not THESES_MD.is_file():
        pytest.skip("../shared/THESES.md is not beside the checkout")
    text = THESES_MD.read_text().split("## 2. Experiments")[1].split("## 3.")[0]
    found = re.findall(r"^\*\*(\d+)(?:-(\d+))?\. ([A-Z]-[^:]+):", text, re.M)
    assert found
    for first, last, name in found:
        numbers = range(int(first), int(last or first) + 1)
        if last:  # "14-16. S-5.3.3-Ex1/Ex2/Ex3"
            stem, *rest = name.split("/")
            names = [stem] + [stem.rsplit("-", 1)[0] + "-" + r for r in rest]
        else:
            names = [name]
        for n, nm in zip(numbers, names):
            assert nm in ids and th.BY_ID[nm].number == n


def curve(variants: dict[str, list[float]], key: str = "loss") -> dict:
    return {"frames": len(next(iter(variants.values()))), "runs": 5,
            "variants": {v: {"rows": [{"frame": i + 1, key: x} for i, x in enumerate(xs)], "final": None}
                         for v, xs in variants.items()}}


def test_density_speedup_verdict():
    frames = 200
    fast = [10 / (f + 1) for f in range(frames)]
    slow6 = [10 / (f / 6 + 1) for f in range(frames)]  # reaches fast's level 6x later
    slow1 = [10 / (f / 1.2 + 1) for f in range(frames)]
    assert th.v_density_speedup(curve({"none": slow6, "density": fast}))[0] == "agrees"
    assert th.v_density_speedup(curve({"none": slow1, "density": fast}))[0] == "disagrees"
    ratio, frame, reached = th.density_speedup(curve({"none": slow6, "density": fast}))
    assert reached and 5 <= ratio <= 7


def test_flicker_and_extra_input_verdicts():
    assert th.v_flicker(curve({"ema 0.99": [0.1] * 10, "no EMA": [0.3] * 10}, "flicker"))[0] == "agrees"
    assert th.v_flicker(curve({"ema 0.99": [0.3] * 10, "no EMA": [0.3] * 10}, "flicker"))[0] == "disagrees"
    assert th.v_extra_inputs(curve({"density": [1.0] * 9, "gradient": [1.1] * 9, "laplacian": [1.05] * 9}))[0] \
        == "agrees"
    assert th.v_extra_inputs(curve({"density": [1.0] * 9, "gradient": [2.0] * 9}))[0] == "disagrees"


def test_colour_verdict_uses_the_settling_frame():
    late, early = [0.2] * 40 + [0.01] * 24, [0.2] * 10 + [0.01] * 54
    assert th.settle_frame(list(range(1, 65)), early, th.CHROMA_GONE) == 11
    assert th.v_colour(curve({"none": late, "density": early}, "chroma"))[0] == "agrees"
    assert th.v_colour(curve({"none": early, "density": late}, "chroma"))[0] == "disagrees"


def timing(times: dict[str, float], steps: dict[str, int] | None = None) -> dict:
    return {"variants": {k: {"time_train_s": t, "train_steps": (steps or {}).get(k, 1)} for k, t in times.items()}}


def test_filter_verdict():
    good = {f"{f}/{v}": t for v in th.VIEWS for f, t in (("none", 1.0), ("stripes", 0.6), ("quadtree", 0.4))}
    steps = {"stripes/none": 0, "quadtree/none": 0}
    assert th.v_filters(timing(good, steps))[0] == "agrees"
    bad = {**good, "quadtree/c": 0.9}
    assert th.v_filters(timing(bad, steps))[0] == "disagrees"
    assert th.v_filters(timing(good, {"stripes/none": 0, "quadtree/none": 2}))[0] == "disagrees"


def test_batch_verdicts():
    def data(per_call: float) -> dict:  # a step of 2^s costs per_call + 2^(s-14) units
        return {"variants": {f"{k}x2^{s}": {"train_s": k * (per_call + 2 ** (s - 14))}
                             for s in (14, 15, 16, 17) for k in range(1, 7)}}

    assert th.v_batch_time(data(2.0))[0] == "agrees"  # a GPU-like fixed cost per call: few large batches win
    assert th.v_batch_time(data(0.0))[0] == "disagrees"  # cost per sample only
    split = {"variants": {f"{2 ** k}x2^{16 - k}": {"train_s": 1.0 + 0.5 * 2 ** k} for k in range(5)}}
    assert th.v_few_large(split)[0] == "agrees"
    flat = {"variants": {f"{2 ** k}x2^{16 - k}": {"train_s": 1.0} for k in range(5)}}
    assert th.v_few_large(flat)[0] == "disagrees"


def test_trace_time_verdict():
    def data(s1: float) -> dict:
        return {"variants": {f"{s}/p{p}/min{m}": {"time_trace_s": (1 + float(p)) * m * (s1 if s == "S1" else 1.0)}
                             for s in ("S0", "S1") for p in ("0.0", "0.25", "0.5", "0.75") for m in (1, 2, 3, 4)}}

    assert th.v_trace_time(data(0.3))[0] == "agrees"
    assert th.v_trace_time(data(1.5))[0] == "disagrees"


def test_nrc_vs_pt_verdicts():
    def data(nrc_mse: float, bias: float) -> dict:
        return {"variants": {"x": {"nrc": {"mse": nrc_mse, "relative_variance": nrc_mse, "thesis_signed_bias": bias},
                                   "pt": {"mse": 1.0, "relative_variance": 1.0, "thesis_signed_bias": 0.0}}}}

    assert th.v_nrc_vs_pt("less_noise")(data(0.7, -0.05))[0] == "agrees"
    assert th.v_nrc_vs_pt("less_noise")(data(1.3, -0.05))[0] == "disagrees"
    assert th.v_nrc_vs_pt("less_noise")(data(0.7, -0.8))[0] == "disagrees"  # far too dark
    assert th.v_nrc_vs_pt("equal")(data(1.06, -0.05))[0] == "agrees"
    assert th.v_nrc_vs_pt("equal")(data(0.3, -0.05))[0] == "disagrees"
    est = {"variants": {e: {"nrc": {"mse": m, "relative_variance": m}} for e, m in
                        (("ratio", 1.0), ("unbiased", 0.8), ("biased", 0.7))}}
    assert th.v_estimators(est)[0] == "agrees"
    est["variants"]["ratio"]["nrc"]["mse"] = 0.5
    assert th.v_estimators(est)[0] == "disagrees"


def test_helpers():
    import numpy as np

    assert th.hydra_value({"a": [1.0, None], "b": "x/y.vdb", "c": True}) == "{a:[1.0,null],b:'x/y.vdb',c:true}"
    ovs = th.scene_overrides({"volume": {"path": "../a.vdb", "g": 0.8}, "lights": [{"type": "point"}]})
    assert ovs == ["scene=base", "scene.volume.path='../a.vdb'", "scene.volume.g=0.8", "scene.lights=[{type:'point'}]"]
    ref = np.ones((2, 2, 3))
    mask = np.ones((2, 2), bool)
    assert th.chroma(ref * 0.5, ref, mask) == pytest.approx(0.0)
    assert th.chroma(ref * [1.0, 1.0, 1.2], ref, mask) == pytest.approx(0.2)
    m, h = th.ci95([1.0, 2.0, None, 3.0])
    assert m == 2.0 and h > 0


def synthetic_result(exp_id: str) -> dict:
    rows = [{"frame": f, **{k: 0.1 for k in ("loss", "rel_mse", "mean_ratio", "chroma", "flicker")},
             **{k + "_ci": 0.01 for k in ("loss", "rel_mse", "mean_ratio", "chroma", "flicker")}} for f in range(1, 9)]
    data = {"frames": 8, "runs": 2, "variants": {v: {"rows": rows, "final": {"mse": 0.1}, "overrides": o}
                                                 for v, o in th.BY_ID[exp_id].variants.items()}}
    return {"id": exp_id, "data": data, "verdict": "disagrees", "reason": "synthetic",
            "ladder": [{"step": "hash lr", "overrides": ["encoding.position.lr=3e-4"], "verdict": "agrees",
                        "reason": "synthetic"}],
            "settings": {"width": 32, "height": 18, "training": [16, 16], "quick": True, "ref_spp": 16},
            "seconds": 1.0, "machine": "test", "threads": 1, "date": "today",
            "command": f"python scripts/theses.py --only {exp_id}"}


def test_page_from_a_synthetic_result(tmp_path, monkeypatch):
    monkeypatch.setattr(th, "OUT", tmp_path)
    exp = th.BY_ID["S-5.3.1"]
    (tmp_path / f"{exp.id}.json").write_text(json.dumps(synthetic_result(exp.id)))
    index = th.report(tmp_path)
    md = (tmp_path / f"{exp.id}.md").read_text()
    assert "**Verdict: disagrees.**" in md and "The step that changes the answer: hash lr" in md
    assert "S:543-547" in md and "conf/experiment/thesis_spindler.yaml" in md
    readme = index.read_text()
    assert "[S-5.3.1](S-5.3.1.md)" in readme and "not run" in readme
    for text in (md, readme):
        assert str(REPO) not in text and "/work/" not in text and "/home/" not in text


def test_a_quick_result_never_stands_in_for_a_measurement(tmp_path):
    path = tmp_path / "x.json"
    assert not th.fresh(path, th.Scale())
    path.write_text(json.dumps(synthetic_result("S-5.3.1")))  # --quick at 32x18
    assert th.fresh(path, th.Scale(width=32, height=18, quick=True))
    assert not th.fresh(path, th.Scale()) and not th.fresh(path, th.Scale(width=32, height=18))


def test_explain_only_runs_the_ladder_of_a_saved_disagreement_without_re_measuring(tmp_path, monkeypatch):
    monkeypatch.setattr(th, "OUT", tmp_path)
    exp = th.BY_ID["S-5.3.1"]
    saved = {**synthetic_result(exp.id), "ladder": []}
    (tmp_path / f"{exp.id}.json").write_text(json.dumps(saved))
    calls = []

    def measure(e, scale, extra=()):  # each ladder step: the cumulative overrides, never the base measurement
        calls.append(list(extra))
        return saved["data"]

    monkeypatch.setitem(th.MEASURE, exp.kind, measure)
    assert th.main(["--explain-only", "--quick", "--quiet", "--only", exp.id]) == 0
    assert calls and all(extra for extra in calls)  # no call without a ladder step's overrides
    res = json.loads((tmp_path / f"{exp.id}.json").read_text())
    assert res["data"] == saved["data"] and [s["step"] for s in res["ladder"]] == [s for s, _ in exp.ladder()[:2]]
    # the measurement's seconds, machine and date stay its own; the ladder's run is recorded beside them
    assert all(res[k] == saved[k] for k in ("seconds", "machine", "date", "command"))
    assert "--explain-only" in res["ladder_run"]["command"] and res["ladder_run"]["seconds"] >= 0
    assert "The ladder re-measured" in th.page(exp, res)
    calls.clear()
    th.main(["--explain-only", "--quick", "--quiet", "--only", exp.id])  # its ladder is there: nothing again
    assert not calls


SCALE_KEYS = {"renderer.training.width", "renderer.training.height",  # the measurement's scale (Scale)
              "renderer.inference.batch_size", "renderer.log.tensorboard"}  # speed and logging only


def _leaves(tree, prefix=""):
    if isinstance(tree, dict):
        for k, v in tree.items():
            yield from _leaves(v, f"{prefix}.{k}" if prefix else k)
    else:
        yield prefix, tree


@pytest.mark.parametrize("exp", [e for e in th.EXPERIMENTS if e.explain], ids=lambda e: e.id)
def test_a_ladder_ends_at_our_defaults(exp):
    """Every variant with all of its ladder's steps has our defaults' cache and renderer settings, but for the
    measurement's scale and the keys its variants set (their subject): a new default that departs from a thesis
    needs a ladder step, or the pages explain a disagreement by settings that are no longer ours."""
    from omegaconf import OmegaConf

    from nrc.config import compose

    scale = th.Scale()
    ours = dict(_leaves(OmegaConf.to_container(compose(["renderer=nrc"]), resolve=True)))
    steps = [o for _, ovs in exp.ladder() for o in ovs]
    for name, variant in exp.variants.items():
        got = dict(_leaves(OmegaConf.to_container(compose(scale.overrides(exp, [*variant, *steps])), resolve=True)))
        off = sorted(k for k in set(got) | set(ours) if k.split(".")[0] in ("cache", "renderer", "extra_inputs")
                     and got.get(k, "<absent>") != ours.get(k, "<absent>") and k not in SCALE_KEYS | exp.subject and k.split(".")[0] not in exp.subject)  # a group: its leaves
        assert not off, f"{exp.id} {name}: the ladder ends away from our defaults at {off}"


def test_bad_input_is_one_line():
    with pytest.raises(SystemExit, match="unknown experiment nope"):
        th.main(["--only", "nope"])
    with pytest.raises(SystemExit, match="--runs must be >= 2"):
        th.main(["--runs", "1"])


@pytest.mark.slow
def test_quick_run_end_to_end(tmp_path, monkeypatch):
    monkeypatch.setattr(th, "OUT", tmp_path)
    assert th.main(["--quick", "--quiet", "--only", "S-5.2-passes"]) == 0
    res = json.loads((tmp_path / "S-5.2-passes.json").read_text())
    assert res["verdict"] in th.VERDICTS and res["settings"]["quick"]
    assert (tmp_path / "S-5.2-passes.md").is_file() and (tmp_path / "README.md").is_file()
