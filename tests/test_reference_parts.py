"""A reference in parts (``nrc.evaluation.reference_parts``, ``python -m nrc.reference_app``): parts merged equal
the one-process reference; a killed part resumes to the same file; parts that do not belong are refused."""

from __future__ import annotations

import logging
import shutil
import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO, compose
from nrc.errors import NRCError
from nrc.evaluation.reference import read_reference, render_reference
from nrc.evaluation.reference_parts import Part, merge_parts, parse_chunks, part_path, parts_dir, render_part

TINY = ["renderer=pt", "renderer.backend=eager", "scene.volume.procedural.resolution=16", "scene.camera.width=6",
        "scene.camera.height=4", "scene.integrator.seed=3"]
CHUNK, TOTAL = 1, 4  # 4 chunks


@pytest.fixture(scope="module")
def one_process(tmp_path_factory):
    """The one-process reference (``render_reference``) of the tiny scene."""
    out = tmp_path_factory.mktemp("one") / "ref.exr"
    render_reference(compose(TINY), out, CHUNK, TOTAL, progress=False)
    return read_reference(out)


@pytest.fixture(scope="module")
def two_parts(tmp_path_factory):
    """The reference ``ref.exr`` rendered as parts 0:1 and 1:4 (a folder the tests copy and change)."""
    out = tmp_path_factory.mktemp("parts") / "ref.exr"
    for a, b in ((0, 1), (1, 4)):
        render_part(compose(TINY), out, CHUNK, TOTAL, range(a, b), progress=False)
    return out


def copy_of(two_parts, tmp_path, keep=("chunks_00000_00001.npz", "chunks_00001_00004.npz")):
    out = tmp_path / "ref.exr"
    parts_dir(out).mkdir()
    for name in keep:
        shutil.copy(parts_dir(two_parts) / name, parts_dir(out) / name)
    return out


def test_parts_merged_equal_the_one_process_reference(one_process, two_parts, tmp_path):
    out = copy_of(two_parts, tmp_path)
    merged = merge_parts(compose(TINY), out, CHUNK, TOTAL)
    ref = read_reference(out)
    np.testing.assert_array_equal(ref.image, merged)
    # float64 sums added part by part instead of chunk by chunk: at most float32 rounding (measured: bitwise)
    np.testing.assert_array_max_ulp(merged, one_process.image, maxulp=1)
    np.testing.assert_array_equal(ref.alpha, one_process.alpha)
    for key in ("spp", "seed", "config_hash", "scene_hash", "chunk_spp"):
        assert ref.attrs[key] == one_process.attrs[key], key
    assert ref.attrs["parts"] == 2
    assert ref.attrs["rel_mse_floor"] == pytest.approx(one_process.attrs["rel_mse_floor"], rel=1e-9)
    # one part of every chunk is the one-process sum itself
    whole = tmp_path / "whole" / "ref.exr"
    render_part(compose(TINY), whole, CHUNK, TOTAL, range(0, 4), progress=False)
    np.testing.assert_array_equal(merge_parts(compose(TINY), whole, CHUNK, TOTAL), one_process.image)


def test_a_killed_part_resumes_to_the_same_file(two_parts, tmp_path):
    cfg = compose(TINY)
    straight = Part.read(part_path(two_parts, range(1, 4)))
    killed = render_part(cfg, tmp_path / "ref.exr", CHUNK, TOTAL, range(1, 4), progress=False, stop_after=2)
    assert killed.done == 2 and not killed.complete
    resumed = render_part(cfg, tmp_path / "ref.exr", CHUNK, TOTAL, range(1, 4), progress=False)
    assert resumed.complete
    again = Part.read(part_path(tmp_path / "ref.exr", range(1, 4)))
    np.testing.assert_array_equal(again.total, straight.total)
    np.testing.assert_array_equal(again.total_sq, straight.total_sq)
    with pytest.raises(NRCError, match=r"misses 1 of 4 chunks; render reference.chunks=0:1 "):
        merge_parts(cfg, tmp_path / "ref.exr", CHUNK, TOTAL)


def test_missing_chunks_are_named_with_the_ranges_to_render(two_parts, tmp_path):
    out = copy_of(two_parts, tmp_path, keep=("chunks_00000_00001.npz",))
    render_part(compose(TINY), out, CHUNK, TOTAL, range(2, 3), progress=False)
    with pytest.raises(NRCError, match=r"misses 2 of 4 chunks; render reference.chunks=1:2, 3:4 "):
        merge_parts(compose(TINY), out, CHUNK, TOTAL)


def test_overlapping_parts_are_refused(two_parts, tmp_path):
    out = copy_of(two_parts, tmp_path)
    render_part(compose(TINY), out, CHUNK, TOTAL, range(0, 2), progress=False)
    with pytest.raises(NRCError, match=r"chunks_00000_00001.npz and chunks_00000_00002.npz overlap"):
        merge_parts(compose(TINY), out, CHUNK, TOTAL)


@pytest.mark.parametrize("other, chunk_spp, total, message", [
    (["scene.volume.albedo=0.5"], CHUNK, TOTAL, "another scene"),
    (["transmittance=residual_ratio"], CHUNK, TOTAL, "another renderer / transmittance config"),
    ([], 2, 2 * TOTAL, "chunk_spp=2, this reference 1"),
    (["scene.integrator.seed=4"], CHUNK, TOTAL, "base seed"),
    ([], CHUNK, 2 * TOTAL, "reference of 8 chunks, this one has 4"),
])
def test_parts_of_another_reference_are_refused(two_parts, tmp_path, other, chunk_spp, total, message):
    out = copy_of(two_parts, tmp_path, keep=("chunks_00001_00004.npz",))
    render_part(compose([*TINY, *other]), out, chunk_spp, total, range(0, 1), progress=False)
    with pytest.raises(NRCError, match=message):
        merge_parts(compose(TINY), out, CHUNK, TOTAL)


def test_seeds_below_the_reference_stream_are_refused(two_parts, tmp_path):
    out = copy_of(two_parts, tmp_path)
    part = Part.read(part_path(out, range(1, 4)))
    part.base_seed = 7
    part.write()
    with pytest.raises(NRCError, match="below the reference stream"):
        merge_parts(compose(TINY), out, CHUNK, TOTAL)


def test_parts_from_another_torch_merge_with_a_warning(two_parts, tmp_path, caplog):
    out = copy_of(two_parts, tmp_path)
    part = Part.read(part_path(out, range(1, 4)))
    part.torch = "0.0.0"
    part.write()
    with caplog.at_level(logging.WARNING):
        merge_parts(compose(TINY), out, CHUNK, TOTAL)
    assert any("different devices / torch versions" in r.getMessage() for r in caplog.records)


def test_a_floor_target_stops_at_it_and_names_the_reference_by_its_spp(tmp_path):
    """``reference.rel_mse_floor``: one process stops at the first chunk count whose noise floor over the medium
    pixels is at most the target; the merged EXR is the one-process reference of that many chunks (bitwise), named
    by its spp, with the target in its header."""
    from nrc.evaluation.reference_parts import merge_to_floor

    six = tmp_path / "six.exr"
    render_reference(compose(TINY), six, CHUNK, 6, progress=False)
    target = read_reference(six).attrs["rel_mse_floor_medium"]  # reached with 6 chunks at the latest
    out = tmp_path / "ref.exr"
    part = render_part(compose(TINY), out, CHUNK, 64, range(64), progress=False, floor_target=target)
    assert 2 <= part.done <= 6
    path = merge_to_floor(compose(TINY), out, CHUNK, 64, target, lambda spp: tmp_path / f"ref_{spp}spp.exr")
    assert path == tmp_path / f"ref_{part.done}spp.exr"
    ref = read_reference(path)
    assert ref.attrs["spp"] == part.done and ref.attrs["rel_mse_floor_medium"] <= target
    assert ref.attrs["rel_mse_floor_target"] == pytest.approx(target)
    same = tmp_path / "same.exr"
    render_reference(compose(TINY), same, CHUNK, part.done, progress=False)
    np.testing.assert_array_equal(ref.image, read_reference(same).image)


def test_a_floor_target_not_reached_names_the_chunks_to_render(two_parts, tmp_path):
    from nrc.evaluation.reference_parts import merge_to_floor

    out = copy_of(two_parts, tmp_path, keep=("chunks_00000_00001.npz",))
    with pytest.raises(NRCError, match=r"has 1 chunks.*about 4 chunks are needed; render reference.chunks=1:4"):
        merge_to_floor(compose(TINY), out, CHUNK, TOTAL, 1e-9, lambda spp: tmp_path / "never.exr")
    assert not (tmp_path / "never.exr").exists()
    (tmp_path / "all").mkdir()
    out = copy_of(two_parts, tmp_path / "all")  # every chunk of the reference, floor still above: written
    path = merge_to_floor(compose(TINY), out, CHUNK, TOTAL, 1e-9, lambda spp: tmp_path / f"r{spp}.exr")
    assert path == tmp_path / "r4.exr" and read_reference(path).attrs["spp"] == 4


def test_chunk_ranges_are_checked():
    assert parse_chunks("all", 6) == range(6) and parse_chunks("2:5", 6) == range(2, 5)
    for bad in ("5:2", "0:7", "x", "1:2:3"):
        with pytest.raises(NRCError, match="reference.chunks"):
            parse_chunks(bad, 6)


def reference_app(cwd, *args, timeout=600, env_dir=None):
    import os

    env = {**os.environ, **({"NRC_REFERENCE_DIR": str(env_dir)} if env_dir else {})}
    return subprocess.run([sys.executable, "-m", "nrc.reference_app", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=timeout, env=env)


@pytest.mark.slow
def test_reference_app_reports_missing_chunks_in_one_line(tmp_path):
    args = [*TINY, "scene.integrator.spp=6", "reference.chunk_spp=1", f"reference.out={tmp_path / 'r.exr'}",
            f"hydra.run.dir={tmp_path / 'run'}"]
    proc = reference_app(REPO, *args, "reference.chunks=0:2")
    assert proc.returncode == 0 and "not merged yet" in proc.stdout, proc.stderr
    proc = reference_app(REPO, *args, "reference.merge=only")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "render reference.chunks=2:6 (each range as a job)" in proc.stderr
    assert parts_dir(tmp_path / "r.exr").is_dir() and not (tmp_path / "r.exr").exists()


@pytest.mark.slow
def test_reference_app_floor_target(tmp_path):
    """One run with ``reference.rel_mse_floor`` renders until the floor, merges into the EXR named by its spp; a bad
    target is one line naming the key."""
    proc = reference_app(REPO, *TINY, "scene.integrator.spp=64", "reference.chunk_spp=2", "reference.rel_mse_floor=0.2",
                         f"hydra.run.dir={tmp_path / 'run'}", "hydra.job.chdir=false",
                         env_dir=tmp_path / "refs")
    assert proc.returncode == 0, proc.stderr[-2000:]
    (exr,) = (tmp_path / "refs").glob("reference_*spp.exr")
    ref = read_reference(exr)
    assert exr.name.endswith(f"_{ref.attrs['spp']}spp.exr") and ref.attrs["spp"] < 64
    assert ref.attrs["rel_mse_floor_medium"] <= 0.2
    proc = reference_app(REPO, *TINY, "reference.rel_mse_floor=-1", f"hydra.run.dir={tmp_path / 'bad'}")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "reference.rel_mse_floor must be > 0.0, got -1.0" in proc.stderr


SPP16 = ["scene.integrator.spp=16", "reference.chunk_spp=1"]


@pytest.fixture(scope="module")
def one_process_16(tmp_path_factory):
    """The 16-chunk reference rendered by one ``python -m nrc.reference_app`` run."""
    tmp = tmp_path_factory.mktemp("one16")
    proc = reference_app(REPO, *TINY, *SPP16, f"reference.out={tmp / 'one.exr'}", f"hydra.run.dir={tmp / 'run'}")
    assert proc.returncode == 0, proc.stderr
    return read_reference(tmp / "one.exr")


@pytest.mark.slow
@pytest.mark.parametrize("launcher", [pytest.param("joblib", marks=pytest.mark.xdist_group("reference16")),
                                      pytest.param("submitit_local", marks=pytest.mark.xdist_group("reference16"))])
def test_a_reference_of_16_chunks_as_4_jobs_equals_one_process(one_process_16, tmp_path, launcher):
    """16 chunks as 4 launcher jobs on 2 workers, merged after the multirun: the one-process reference."""
    split = tmp_path / "split.exr"
    workers = ["hydra.launcher.n_jobs=2"] if launcher == "joblib" else []
    proc = reference_app(REPO, "-m", *TINY, *SPP16, f"reference.out={split}", f"hydra/launcher={launcher}", *workers,
                         "reference.chunks=0:4,4:8,8:12,12:16", f"hydra.sweep.dir={tmp_path / 'sweep'}")
    assert proc.returncode == 0, proc.stderr
    a, b = one_process_16, read_reference(split)
    assert b.attrs["parts"] == 4 and b.attrs["spp"] == 16
    np.testing.assert_array_max_ulp(b.image, a.image, maxulp=1)
    print(f"{launcher}: largest difference {np.abs(b.image - a.image).max():.3g}, "
          f"{int((b.image != a.image).sum())} of {a.image.size} values differ")


def test_ensure_reference_renders_once_and_returns_the_path(tmp_path, monkeypatch):
    """``nrc.reference_app.ensure_reference`` (what the lab's tools call): the default path under the working
    directory, rendered when missing, returned as it is when present."""
    from nrc.reference_app import ensure_reference

    monkeypatch.delenv("NRC_REFERENCE_DIR", raising=False)
    monkeypatch.chdir(tmp_path)
    overrides = ["renderer=pt", "scene.volume.procedural.resolution=16", "scene.camera.width=6",
                 "scene.camera.height=4"]
    path = ensure_reference(overrides, 8, 4)
    assert path.parent == tmp_path / "data" / "references" and read_reference(path).attrs["spp"] == 8
    stamp = path.stat().st_mtime_ns
    assert ensure_reference(overrides, 8, 4) == path and path.stat().st_mtime_ns == stamp
