"""The README's generated figure captions (``scripts/experiments_report.py --results``, code in
:mod:`nrc.evaluation.experiments`): built from made-up result files in a temp dir, written between their markers
only, idempotent, and a missing marker is one error line."""

from __future__ import annotations

import json

import pytest

from conftest import load_script
from nrc.evaluation import experiments as ex

BEFORE = "# A project\n\nHand-written text, 1.7x and all.\n\n![a figure](docs/images/clouds.png)\n\n*Its caption.*\n"
AFTER = "\n## Later\nMore hand-written text.\n"


def summary(ratio: float, mean: float, warmup: int) -> dict:
    """A ``speed_vs_error`` summary with NRC + OIDN against the path tracer + OIDN at equal time."""
    rows = [{"mode": "single", "config": "nrc+oidn", "renderer": "nrc", "denoised": True, "spp": 1, "time_s": 0.5,
             "mean_ratio_medium": mean},
            *({"mode": "single", "config": "pt_compiled+oidn", "renderer": "pt", "denoised": True, "spp": spp,
               "time_s": t, "mean_ratio_medium": 0.99} for spp, t in ((1, 0.3), (8, 0.9)))]
    ratios = [{"config": "nrc+oidn", "baseline": "pt+oidn", "time_s": 0.5, "ratio_rel_mse_medium": ratio,
               "pt_rel_mse_medium": 0.002},
              {"config": "nrc", "baseline": "pt", "time_s": 0.45, "ratio_rel_mse_medium": 0.5, "pt_rel_mse_medium": 0.1}]
    return {"meta": {"argv": ["--warmup", str(warmup), "--out", "x"], "wall_time_s": 12.0}, "rows": rows,
            "equal_time": ratios}


COMPARISON = {
    "scene": "a made-up cloud", "comparison": "side_lit", "width": 160, "height": 90, "reference_spp": 256,
    "reference_rel_mse_floor_medium": 1e-4,
    "pt": {"rel_mse_medium": 0.05, "mean_over_reference_medium": 0.99, "spp": 8, "time_s": 0.61},
    "nrc": {"rel_mse_medium": 0.06, "mean_over_reference_medium": 0.95, "spp_per_frame": 4, "frames": 12,
            "time_per_frame_s": 0.62, "time_all_frames_s": 9.0},
    "pt_oidn": {"rel_mse_medium": 0.002, "mean_over_reference_medium": 0.98, "time_denoise_s": 0.03,
                "rel_mse_medium_per_seed": {"11": 0.002, "12": 0.0019, "13": 0.003}},
    "nrc_oidn": {"rel_mse_medium": 0.01, "mean_over_reference_medium": 0.94, "time_denoise_s": 0.02},
}


@pytest.fixture
def docs(tmp_path):
    d = tmp_path / "docs"
    for name, s in {"oidn_160x90_side_lit": summary(3.5, 0.95, 30), "oidn_160x90_cumulus": summary(1.3, 1.02, 30),
                    "oidn_160x90_side_lit_warm": summary(1.5, 0.99, 150)}.items():
        (d / "results" / name).mkdir(parents=True)
        (d / "results" / name / "summary.json").write_text(json.dumps(s))
        (d / "results" / name / "speed_vs_error.md").write_text("| a table |")
    (d / "images").mkdir()
    (d / "images" / "nrc_vs_pt.json").write_text(json.dumps(COMPARISON))
    figures = {"heroes": {"cumulus": {"spp": 64, "rel_mse_floor": 0.004, "time_s": 10.0},
                          "disney": {"spp": 64, "rel_mse_floor": 0.002, "time_s": 11.0}},
               "machine": "test machine", "skipped": ["heroes"], "comparison": COMPARISON,
               "animation": {"frames": 12, "warmup_frames": 3, "degrees_per_frame": 30.0, "pt_spp": 5,
                             "pt_time_per_frame_s": 0.41, "nrc_time_per_frame_s": 0.52}}
    (d / "images" / "figures.json").write_text(json.dumps(figures))
    return d


def readme(names=("crossover", "clouds", "nrc_vs_pt", "sun"), body: str = "old numbers, 9.4x") -> str:
    blocks = "".join(f"\n{ex.README_BEGIN.format(n)}\n{body}\n{ex.README_END}\n\nbetween\n" for n in names)
    return BEFORE + blocks + AFTER


def test_blocks_carry_the_result_files_numbers_with_their_conditions(docs):
    blocks = {k: " ".join(ex.block_markdown(v)) for k, v in ex.readme_blocks(docs).items()}
    clouds, cmp, sun = blocks["clouds"], blocks["nrc_vs_pt"], blocks["sun"]
    assert "64-spp path trace" in clouds and "0.002 (the Disney cloud) to 0.004 (cumulus)" in clouds
    assert "test machine" not in clouds and "rendered in" not in clouds  # the last run skipped the heroes
    assert "a made-up cloud, 160 x 90, one run (test machine)" in cmp and "12 frames at 4 spp" in cmp
    assert "8 spp in 0.61 s" in cmp and "256-spp reference, whose own noise adds 0.0001" in cmp
    assert "**0.002** (the median of 3 seeds, 0.0019–0.003)" in cmp and "**0.01**, 5x the path tracer's" in cmp
    assert "NRC + OIDN 0.940, the path tracer + OIDN 0.980" in cmp
    # the equal-time runs: the ranges by warm-up, the image means, the verdict and the figure's own scene
    assert "is 1.3x (the default cumulus" in cmp and "to 3.5x (side-lit Disney cloud" in cmp
    assert "after 30 warm-up frames" in cmp and "and 1.5x (side-lit Disney cloud, 160 x 90, a warm cache) after 150" in cmp
    assert "NRC scored at 1 spp a frame" in cmp and "from its 1–8-spp renders" in cmp
    assert "image mean over the cloud's pixels is 0.95–1.02" in cmp and "ahead on every run" in cmp
    assert "they measure 3.5x (image mean 0.95); the figure is a single run at 4 spp" in cmp
    assert "12 frames, the sun 30 degrees further" in sun and "5 spp afresh every frame in 0.41 s" in sun
    assert "takes 0.52 s" in sun and "recorded frames; test machine)" in sun  # the last run made the animation
    figures = json.loads((docs / "images" / "figures.json").read_text())
    assert ex.readme_animation({**figures, "skipped": ["heroes", "animation"]}) == ex.readme_animation(
        {k: v for k, v in figures.items() if k != "machine"})


def test_verdict_follows_the_ratios(docs):
    summaries = {"oidn_160x90_side_lit": ("side-lit", summary(0.8, 1.0, 30)),
                 "oidn_160x90_cumulus": ("cumulus", summary(2.0, 1.0, 30))}
    assert "NRC + OIDN is ahead on 1 of 2 runs" in ex.sweep_summary(summaries)
    assert ex.sweep_summary({"speed_160x90_v2": ("old", summary(2.0, 1.0, 30))}) is None


def test_missing_result_files_say_so(tmp_path):
    blocks = ex.readme_blocks(tmp_path)
    assert all(len(v) == 1 and v[0].startswith("(not measured") for v in blocks.values())


def test_results_rewrites_the_readme_block_only_and_is_idempotent(docs, tmp_path, capsys):
    path = tmp_path / "README.md"
    path.write_text(readme())
    args = ["batch_filters", "--results", "--docs", str(docs), "--root", str(tmp_path / "none"),
            "--intro", str(tmp_path / "no_intro.md"), "--readme", str(path)]
    assert load_script("experiments_report").main(args) == 0
    text = path.read_text()
    assert text.startswith(BEFORE) and text.endswith(AFTER) and "9.4x" not in text
    for name in ("crossover", "clouds", "nrc_vs_pt", "sun"):
        assert text.count(ex.README_BEGIN.format(name)) == 1
    assert text.count(ex.README_END) == 4 and text.count("\nbetween\n") == 4
    # the README and docs/results.md state the same ratios (one source)
    results = (docs / "results.md").read_text()
    assert "relMSE ratio **3.5**" in results and "to 3.5x (side-lit" in text.replace("\n", " ")
    assert "1.3 (mean 1.02)" in results and "is 1.3x (the default cumulus" in text.replace("\n", " ")
    # docs/results.md is a short summary; each run has its own page, linked from it
    assert len(results.splitlines()) <= 150 and "](results/oidn_160x90_side_lit/README.md)" in results
    page = (docs / "results" / "oidn_160x90_side_lit" / "README.md").read_text()
    assert "| a table |" in page and "| a table |" not in results and "![speed vs error" in page
    # no generated line would start a Markdown list or heading
    generated = text[len(BEFORE):-len(AFTER)].splitlines()
    assert len(generated) > 10 and not any(line.startswith(("+", "-", "#")) for line in generated)
    capsys.readouterr()
    assert load_script("experiments_report").main(args) == 0
    assert path.read_text() == text and "generated figure captions unchanged" in capsys.readouterr().out


def test_a_missing_marker_is_one_error_line(docs, tmp_path):
    path = tmp_path / "README.md"
    path.write_text(readme(names=("crossover", "clouds", "nrc_vs_pt")))
    with pytest.raises(SystemExit) as e:
        load_script("experiments_report").main(["batch_filters", "--results", "--docs", str(docs),
                                                 "--root", str(tmp_path / "none"), "--readme", str(path)])
    msg = str(e.value)
    assert msg.startswith("experiments_report: README.md: no line `<!-- generated: scripts/experiments_report.py "
                          "--results: sun -->`") and "\n" not in msg
    assert path.read_text() == readme(names=("crossover", "clouds", "nrc_vs_pt"))  # nothing written
    assert not (docs / "results.md").exists() and not (docs / "results" / "batch_filters.md").exists()


@pytest.mark.parametrize("text, says", [
    (readme() + ex.README_BEGIN.format("sun") + "\n", "appears 2 times"),
    (readme().replace(ex.README_END + "\n\nbetween\n" + AFTER, "\n" + AFTER), "has no `<!-- end generated -->`"),
    (readme() + ex.README_BEGIN.format("typo") + "\n" + ex.README_END + "\n", "unknown generated block"),
])
def test_bad_markers_are_named(text, says):
    with pytest.raises(ex.ReadmeError, match=says):
        ex.rewrite_readme(text, {"crossover": ["x"], "clouds": ["a"], "nrc_vs_pt": ["b"], "sun": ["c"]})


def test_wrap_never_starts_a_line_with_a_list_marker():
    lines = ex.block_markdown(["NRC + OIDN - 1. the path tracer + OIDN " * 20])
    assert len(lines) > 5 and not any(line.startswith(("+", "-", "1.")) for line in lines)
    assert lines[0].startswith("*NRC") and lines[-1].endswith("OIDN*")


def test_a_report_without_runs_keeps_its_committed_markdown(tmp_path):
    (tmp_path / "docs" / "results").mkdir(parents=True)
    kept = tmp_path / "docs" / "results" / "batch_filters.md"
    kept.write_text("measured table")
    assert load_script("experiments_report").main(["batch_filters", "--docs", str(tmp_path / "docs"), "--root", str(tmp_path / "none")]) == 0
    assert kept.read_text() == "measured table"


def crossover_map(d, ratios, name=ex.CROSSOVER):
    """A made-up ``scripts/crossover_map.py`` output: ``ratios`` = [(tau, albedo, NRC+OIDN / PT+OIDN)]."""
    out = d / "results" / name
    out.mkdir(parents=True, exist_ok=True)
    pts = [{"point": f"p{i}", "tau_median": tau, "albedo": a, "ratio_oidn": r, "ratio_raw": 2 * r,
            "nrc_mean_ratio_medium": 0.97} for i, (tau, a, r) in enumerate(ratios)]
    (out / "map.json").write_text(json.dumps({"argv": ["--out", "x"], "points": pts}))
    (out / "map.md").write_text("| point | ... |\n|---|---|\n")


def test_crossover_summary_states_where_nrc_pays_off(tmp_path):
    assert ex.crossover_summary(tmp_path) is None and ex.crossover_section(tmp_path) == []
    crossover_map(tmp_path, [(7.0, 0.99, 3.0), (98.0, 0.99, 0.8), (196.0, 0.99, 0.5), (98.0, 1.0, 0.6)])
    text = ex.crossover_summary(tmp_path)
    assert "at albedo 0.99: 3x at optical depth 7, 0.8x at optical depth 98, 0.5x at optical depth 196" in text
    assert "at albedo 1: 0.6x at optical depth 98" in text
    assert "ahead at 3 of 4 points, from optical depth 98 (albedo 0.99) on" in text
    assert "raw NRC over the raw path tracer 1–6x" in text and "image mean 0.97 of the reference's" in text
    crossover_map(tmp_path, [(7.0, 0.99, 3.0), (98.0, 0.99, 1.5)])
    assert "beats the path tracer + OIDN nowhere on the map" in ex.crossover_summary(tmp_path)
    assert ex.crossover_section(tmp_path)[0].startswith("## Where NRC pays off")
    crossover_map(tmp_path, [(98.0, 0.99, 0.7)], ex.CROSSOVER + "_warm")
    assert "With a warm cache (150 warm-up frames): 0.7x at optical depth 98 (albedo 0.99, image mean 0.97)" in \
        ex.crossover_summary(tmp_path)
    assert any("A warm cache" in line for line in ex.crossover_section(tmp_path))
    assert ex.crossover_figure(tmp_path) is None  # no plot yet
    (tmp_path / "results" / ex.CROSSOVER / "map.png").write_bytes(b"png")
    image, caption = ex.crossover_figure(tmp_path)
    assert image == f"[![Where NRC pays off: the crossover map](docs/results/{ex.CROSSOVER}/map.png)](docs/results.md)"
    assert "NRC wins nowhere (best 1.5x at optical depth 98, albedo 0.99)" in caption
    assert "warm cache: 0.7x at optical depth 98" in caption
    lines = ex.block_markdown([image, caption])
    assert lines[0] == image and lines[1] == "" and len(lines) == 4  # the plot and a caption of two lines
    crossover_map(tmp_path, [(98.0, 0.99, 1.2)], "crossover_480x270")
    assert "At 480 x 270: 1.2x at optical depth 98 (albedo 0.99" in ex.crossover_summary(tmp_path)
    assert any(line.startswith("**At 480 x 270**") for line in ex.crossover_section(tmp_path))
    a = tmp_path / "results" / ex.ANIMATION
    a.mkdir(parents=True)
    rows = [{"config": "pt", "spp": 1, "whole_oidn_s": 70.0},
            {"config": "nrc", "whole_oidn_s": 66.0, "ratio_vs_pt_oidn": 0.8, "ratio_vs_pt": 0.2,
             "extrapolated_oidn": False}]
    (a / "summary.json").write_text(json.dumps({"meta": {"argv": ["--frames", "60", "--preset", "thick"]},
                                                "animation": {"rows": rows, "frames": 60,
                                                              "scored_frames": [9, 19, 29, 39, 49, 59]}}))
    (a / "animation.md").write_text("| the table |")
    text = ex.crossover_summary(tmp_path)
    assert "A whole 60-frame animation of the turning sun (`scene=thick`, every 10th frame scored" in text
    assert "takes NRC 66 s with OIDN, and its error is 0.8x the path tracer + OIDN's" in text
    assert "| the table |" in ex.crossover_section(tmp_path)
