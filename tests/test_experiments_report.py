"""The README's generated block and docs/results.md (``scripts/experiments_report.py --results``): built from
made-up result files in a temp dir, written between the block's markers only, idempotent, and a missing marker is
one error line."""

from __future__ import annotations

import json

import pytest

from conftest import load_script

ex = load_script("experiments_report")

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


def crossover_map(d, ratios, name=ex.CROSSOVER, points=None, argv=("--out", "x")):
    """A made-up ``scripts/crossover_map.py`` output: ``ratios`` = [(tau, albedo, NRC+OIDN / PT+OIDN)]."""
    out = d / "results" / name
    out.mkdir(parents=True, exist_ok=True)
    names = points or [f"p{i}" for i in range(len(ratios))]
    pts = [{"point": n, "tau_median": tau, "albedo": a, "ratio_oidn": r, "ratio_raw": 2 * r,
            "nrc_mean_ratio_medium": 0.97, "nrc+oidn_mean_ratio_medium": 0.95}
           for n, (tau, a, r) in zip(names, ratios)]
    (out / "map.json").write_text(json.dumps({"argv": list(argv), "points": pts}))
    (out / "map.md").write_text("| point | ... |\n|---|---|\n")


@pytest.fixture
def docs(tmp_path):
    d = tmp_path / "docs"
    for name, s in {"oidn_160x90_side_lit": summary(3.5, 0.95, 30), "oidn_160x90_cumulus": summary(1.3, 1.02, 30),
                    "oidn_160x90_side_lit_warm": summary(1.5, 0.99, 150)}.items():
        (d / "results" / name).mkdir(parents=True)
        (d / "results" / name / "summary.json").write_text(json.dumps(s))
        (d / "results" / name / "speed_vs_error.md").write_text("| a table |")
    crossover_map(d, [(7.0, 0.99, 7.9), (98.0, 0.99, 1.7), (196.0, 0.99, 1.5), (98.0, 0.95, 1.1)])
    crossover_map(d, [(98.0, 0.99, 0.77), (196.0, 0.99, 0.67)], ex.CROSSOVER + "_warm", points=("p1", "p2"),
                  argv=["--out", "x", "--warmup", "150", "--points", "p1,p2"])
    return d


def readme(names=("results",), body: str = "old numbers, 9.4x") -> str:
    blocks = "".join(f"\n{ex.README_BEGIN.format(n)}\n{body}\n{ex.README_END}\n\nbetween\n" for n in names)
    return BEFORE + blocks + AFTER


def test_the_block_states_the_finding_a_table_and_the_map(docs):
    lines = ex.readme_results(docs)
    blank = lines.index("")
    sentence = " ".join(lines[:blank])
    assert "after 30 warm-up frames from an untrained cache is higher at every point of the crossover map" in sentence
    assert "from 1.1x at optical depth 98 (albedo 0.95) to 7.9x at optical depth 7 (albedo 0.99)" in sentence
    assert "with a warm cache (150 frames) it wins at 2 of the 2 points measured: 0.77x at optical depth 98, " \
           "0.67x at optical depth 196" in sentence
    assert "; without a denoiser the raw NRC frame's relMSE is 2.2–16x the raw path tracer's at equal time after 30 " \
           "frames" in sentence
    assert sentence.count(". ") == 0 and sentence.endswith("(below 1: NRC wins).")  # one sentence
    table = [line for line in lines if line.startswith("|")]
    assert table[0].startswith("| point | optical depth | albedo | NRC+OIDN / PT+OIDN, 30 frames | "
                               "NRC+OIDN / PT+OIDN, 150 frames (warm) | NRC / PT raw, 30 frames | "
                               "NRC+OIDN image mean / reference's, 30 frames |")
    rows = {r.split("|")[1].strip(): [c.strip() for c in r.split("|")[2:-1]] for r in table[2:]}
    assert rows["p0"] == ["7", "0.99", "7.9", "–", "16", "0.95"]
    assert rows["p1"] == ["98", "0.99", "1.7", "0.77", "3.4", "0.95"]
    assert list(rows) == ["p3", "p0", "p1", "p2"]  # by albedo, then optical depth
    assert lines[-1] == f"[![Where NRC pays off: the crossover map](docs/results/{ex.CROSSOVER}/map.png)](docs/results.md)"


def test_a_missing_map_says_so(tmp_path):
    (line,) = ex.readme_results(tmp_path)
    assert line.startswith("(not measured") and "crossover_map.py" in line


def test_results_rewrites_the_readme_block_only_and_is_idempotent(docs, tmp_path, capsys):
    path = tmp_path / "README.md"
    path.write_text(readme())
    args = ["--results", "--docs", str(docs),
            "--intro", str(tmp_path / "no_intro.md"), "--readme", str(path)]
    assert load_script("experiments_report").main(args) == 0
    text = path.read_text()
    assert text.startswith(BEFORE) and text.endswith(AFTER) and "9.4x" not in text
    assert text.count(ex.README_BEGIN.format("results")) == 1 and text.count(ex.README_END) == 1
    # the README and docs/results.md state the same ratios (one source: the crossover maps)
    results = (docs / "results.md").read_text()
    assert "| p1 | 98 | 0.99 | 1.7 | 0.77 |" in text and "1.7x at optical depth 98" in results
    assert "relMSE ratio **3.5**" in results and "1.3 (mean 1.02)" in results
    # docs/results.md is a short summary; each run has its own page, linked from it
    assert len(results.splitlines()) <= 150 and "](results/oidn_160x90_side_lit/README.md)" in results
    page = (docs / "results" / "oidn_160x90_side_lit" / "README.md").read_text()
    assert "| a table |" in page and "| a table |" not in results and "![speed vs error" in page
    # no generated line would start a Markdown list or heading
    generated = text[len(BEFORE):-len(AFTER)].splitlines()
    assert len(generated) > 10 and not any(line.startswith(("+", "-", "#")) for line in generated)
    capsys.readouterr()
    assert load_script("experiments_report").main(args) == 0
    assert path.read_text() == text and "its generated block unchanged" in capsys.readouterr().out


def test_a_missing_marker_is_one_error_line(docs, tmp_path):
    path = tmp_path / "README.md"
    path.write_text(readme(names=()))
    with pytest.raises(SystemExit) as e:
        load_script("experiments_report").main(["--results", "--docs", str(docs), "--readme", str(path)])
    msg = str(e.value)
    assert msg.startswith("experiments_report: README.md: no line `<!-- generated: scripts/experiments_report.py "
                          "--results: results -->`") and "\n" not in msg
    assert path.read_text() == readme(names=())  # nothing written
    assert not (docs / "results.md").exists()


@pytest.mark.parametrize("text, says", [
    (readme() + ex.README_BEGIN.format("results") + "\n", "appears 2 times"),
    (readme().replace(ex.README_END + "\n\nbetween\n" + AFTER, "\n" + AFTER), "has no `<!-- end generated -->`"),
    (readme() + ex.README_BEGIN.format("clouds") + "\n" + ex.README_END + "\n", "unknown generated block"),
])
def test_bad_markers_are_named(text, says):
    with pytest.raises(ex.ReadmeError, match=says):
        ex.rewrite_readme(text, {"results": ["x"]})


def test_wrap_never_starts_a_line_with_a_list_marker():
    lines = ex._wrap("NRC + OIDN - 1. the path tracer + OIDN " * 20)
    assert len(lines) > 5 and not any(line.startswith(("+", "-", "1.")) for line in lines)


def test_without_results_it_says_where_the_thesis_experiments_went(tmp_path):
    with pytest.raises(SystemExit, match="scripts/theses.py"):
        load_script("experiments_report").main(["--docs", str(tmp_path / "docs")])


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
    crossover_map(tmp_path, [(98.0, 0.99, 1.2)], "crossover_480x270")
    assert "At 480 x 270: 1.2x at optical depth 98 (albedo 0.99" in ex.crossover_summary(tmp_path)
    assert any(line.startswith("**At 480 x 270**") for line in ex.crossover_section(tmp_path))
    a = tmp_path / "results" / ex.ANIMATION
    a.mkdir(parents=True)
    rows = [{"config": "pt", "spp": 1, "whole_oidn_s": 70.0},  # a variant first: the summary quotes the defaults' row
            {"config": "nrc_quarter", "whole_oidn_s": 60.0, "ratio_vs_pt_oidn": 0.9, "ratio_vs_pt": 0.3,
             "extrapolated_oidn": False},
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


def test_an_accumulated_run_stays_out_of_the_single_frame_table():
    """An accumulated run (``--mode accumulate``) has equal-time ratios but no single NRC + OIDN frame: the
    scene-type table skips it instead of failing."""
    single = summary(1.3, 1.02, 30)
    accumulated = {**summary(0.9, 0.99, 30), "rows": [{**r, "mode": "accumulate"} for r in single["rows"]]}
    table = ex.scene_type_table({"oidn_160x90_cumulus": ("cumulus", single),
                                 "oidn_160x90_side_lit_accumulate": ("side-lit, accumulated", accumulated)})
    rows = [line for line in table if line.startswith("| ") and not line.startswith("| run")]
    assert len(rows) == 1 and rows[0].startswith("| cumulus") and "**1.3**" in rows[0]
