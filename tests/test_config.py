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


def test_auto_or_number_keys():
    """``ConfigReader.get_int_or_auto`` / ``get_float_or_auto``: ``auto`` reads as None (also as the default), a
    number as ``get_int`` / ``get_float`` read it with their bounds; another word names the key and what it takes."""
    from nrc.config import ConfigReader
    from nrc.errors import ConfigError

    r = ConfigReader({"a": "auto", "b": 3, "c": 0.5, "d": "autoo", "e": -1}, "blk")
    assert r.get_int_or_auto("a") is None
    assert r.get_int_or_auto("b", lo=0) == 3
    assert r.get_float_or_auto("c", lo=0.0, hi=1.0) == 0.5
    assert r.get_int_or_auto("missing", "auto") is None
    assert r.get_float_or_auto("missing2", 0.25) == 0.25
    with pytest.raises(ConfigError, match=r"blk\.d must be auto or an integer, got 'autoo'"):
        r.get_int_or_auto("d")
    with pytest.raises(ConfigError, match=r"blk\.d must be auto or a number"):
        r.get_float_or_auto("d")
    with pytest.raises(ConfigError, match=r"blk\.e must be >= 0"):
        r.get_int_or_auto("e", lo=0)
    with pytest.raises(ConfigError, match=r"blk\.missing3 is required"):
        r.get_float_or_auto("missing3")
    r.finish()  # every key was asked for
