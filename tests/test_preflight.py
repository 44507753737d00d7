"""Every value checked before work starts (``nrc.app.preflight``): one error naming the key or the file, raised
before a scene is built; and the app's own checks of its run directory."""

from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import REPO, compose
from nrc import app
from nrc.errors import NRCError

BAD = [
    (["frames=abc", "renderer=nrc"], "frames must be an integer"),
    (["frames=0", "renderer=nrc"], "frames must be >= 1"),
    (["frames=2.5"], "frames must be an integer"),
    (["device=gpu"], "device must be 'cpu' or 'cuda[:N]'"),
    (["device=tpu"], "device must be"),
    (["tonemap=filmic"], "tonemap must be one of"),
    (["exposure=-1"], "exposure must be 'auto' or a positive finite number"),
    (["denoise=magic"], "denoise"),
    (["renderer.name=bogus"], "renderer.name must be one of"),
    (["renderer.backend=fast"], "renderer.backend"),
    (["renderer.slots=0"], "renderer.slots must be >= 1"),
    (["renderer.slots=many"], "renderer.slots must be an integer"),
    (["+renderer.typo=1"], "unknown key(s) typo"),
    (["renderer=nrc", "renderer.training.records_per_path=0"], "renderer.training.records_per_path must be >= 1"),
    (["renderer=nrc", "renderer.termination.rule=depth"], "renderer.termination.rule must be one of"),
    (["renderer=nrc", "renderer.reference=/no/such/reference.exr"], "renderer.reference=/no/such/reference.exr: no such file"),
    (["renderer=nrc", "renderer.resume=/no/such/checkpoint.pt"], "renderer.resume=/no/such/checkpoint.pt: no such file"),
    (["renderer=nrc", "renderer.resume=/tmp"], "renderer.resume=/tmp: not a file"),
    (["scene.volume.source=vdb", "scene.volume.path=/no/such/cloud.vdb"], "scene.volume.path=/no/such/cloud.vdb: no such file"),
    (["scene.volume.source=npz", "scene.volume.path=/no/such/cloud.npz"], "scene.volume.path"),
    (["scene=sky", "scene.lights.0.radiance=null", "scene.lights.0.path=/no/such/env.exr"], "scene.lights[0].path"),
    (["renderer=nrc", "renderer.debias.probability=2"], "renderer.debias.probability"),
    (["renderer=preview", "+renderer.nope=1"], "unknown key(s) nope"),
]


@pytest.mark.parametrize("overrides, message", BAD, ids=lambda v: " ".join(v) if isinstance(v, list) else None)
def test_bad_values_are_one_error_before_the_scene_is_built(overrides, message, monkeypatch):
    def no_scene(*a, **k):
        raise AssertionError("the scene was built before the values were checked")

    monkeypatch.setattr("nrc.scene.load_scene", no_scene)
    cfg = compose(overrides)
    with pytest.raises(NRCError) as err:
        app.preflight(cfg)
    assert message in str(err.value), str(err.value)
    assert "\n" not in str(err.value)


def test_good_configs_pass():
    for overrides in ([], ["renderer=nrc"], ["renderer=preview"], ["scene=many_lights", "renderer=nrc"]):
        app.preflight(compose(overrides))


def test_a_run_directory_that_cannot_be_created_is_one_line(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    for target, message in ((blocker / "run", "is a file"), ("/proc/nrc-run", "cannot create the run directory")):
        proc = subprocess.run([sys.executable, "-m", "nrc", f"hydra.run.dir={target}"], cwd=REPO,
                              capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2 and message in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert app.run_dir_problem(["--help", "hydra.run.dir=/proc/x"]) is None  # --help writes nothing


def test_help_opens_with_what_nrc_is():
    proc = subprocess.run([sys.executable, "-m", "nrc", "--help"], cwd=REPO, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0
    assert proc.stdout.startswith("nrc renders clouds") and "renderer=pt|nrc|preview" in proc.stdout
