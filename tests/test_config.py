"""``nrc.config.compose``: its cache of group compositions gives exactly Hydra's config, and Hydra's errors."""

from __future__ import annotations

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from nrc.config import CONF_DIR, _hydra_compose, compose

SCENES = sorted(p.stem for p in (Path(CONF_DIR) / "scene").glob("*.yaml"))
EXPERIMENTS = sorted(p.stem for p in (Path(CONF_DIR) / "experiment").glob("*.yaml"))
CASES = [
    [],
    *[[f"scene={s}", f"renderer={r}"] for s in SCENES for r in ("pt", "nrc", "preview")],
    *[[f"+experiment={e}"] for e in EXPERIMENTS],
    ["renderer=nrc", "scene.integrator.seed=3", "scene.camera.width=8", "encoding=triangle_oneblob",
     "extra_inputs=all", "batch_filter=quadtree", "transmittance=track_length"],
    ["scene.integrator.seed=3", "scene=sun_sky"],  # a value before its group: groups first, as Hydra does
    ["scene.lights=[{type:directional,direction:[-0.6,-0.55,-0.35],irradiance:[2.6,2.5,2.3]},"
     "{type:point,position:[0,-45,10],intensity:[900,700,500]}]", "renderer.backend=eager"],
    ["renderer=nrc", "+renderer.new_key=3", "~renderer.reuse", "++frames=7", "scene.volume.path=null"],
    ["scene.volume.density_scale=${scene.volume.albedo}"],
]


@pytest.mark.parametrize("overrides", CASES, ids=lambda o: " ".join(o)[:60] or "defaults")
def test_cached_composition_is_hydras(overrides):
    got, want = compose(overrides), _hydra_compose(overrides)
    assert OmegaConf.to_container(got) == OmegaConf.to_container(want)
    assert OmegaConf.is_struct(got) == OmegaConf.is_struct(want)
    got.scene.integrator.seed = 12345  # a caller's change stays in its own copy
    assert compose(overrides).scene.integrator.seed == want.scene.integrator.seed


@pytest.mark.parametrize("overrides", [["scene.volume.typo=3"], ["scene=nope"], ["scene.camera.width=[1,"],
                                       ["+experiment=nope"], ["renderer=pt", "~renderer.nothing"]])
def test_errors_are_hydras(overrides):
    with pytest.raises(Exception) as want:
        _hydra_compose(overrides)
    with pytest.raises(type(want.value)) as got:
        compose(overrides)
    assert str(got.value) == str(want.value)


def test_the_hydra_node_goes_through_hydra():
    cfg = compose(["hydra.run.dir=somewhere"], return_hydra_config=True)
    assert cfg.hydra.run.dir == "somewhere"


def test_transport_keys_shared_by_pt_and_nrc_live_in_one_file():
    """renderer=pt and renderer=nrc include conf/renderer/shared/wavefront.yaml: neither repeats one of its keys
    (one home for each default), and both compose them at the same paths."""
    from omegaconf import OmegaConf

    from conftest import CONF_DIR, compose

    shared = OmegaConf.load(CONF_DIR / "renderer" / "shared" / "wavefront.yaml")
    for name in ("pt", "nrc"):
        own = OmegaConf.load(CONF_DIR / "renderer" / f"{name}.yaml")
        assert not set(own) & set(shared), f"{name}.yaml repeats {set(own) & set(shared)}"
        composed = compose([f"renderer={name}"]).renderer
        assert {k: composed[k] for k in shared} == dict(shared) and composed.name == name
