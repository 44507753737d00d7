"""Config groups of the cache: Hydra composition of every encoding and extra-inputs file, validation errors."""

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from nrc.cache import build_radiance_cache
from nrc.cache.encodings.factory import auto_log2_hashmap_size
from nrc.cache.encodings.hashgrid import HashGridEncoding
from nrc.errors import ConfigError
from nrc.volume.grid import DensityGrid

CONF = Path(__file__).resolve().parent.parent / "conf"
ENCODINGS = sorted(p.stem for p in (CONF / "encoding").glob("*.yaml"))
EXTRAS = sorted(p.stem for p in (CONF / "extra_inputs").glob("*.yaml"))


def _grid() -> DensityGrid:
    return DensityGrid(torch.rand(8, 6, 5), center=(0, 0, 0), diagonal=2.0, density_scale=1.0)


def _compose(encoding: str, extras: str, overrides: tuple[str, ...] = ()):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(overrides=["+cache=default", f"+encoding={encoding}", f"+extra_inputs={extras}", *overrides])


def test_config_files_present():
    assert {"hashgrid_oneblob", "triangle_oneblob", "frequency_oneblob", "identity"} <= set(ENCODINGS)
    assert {"none", "density", "gradient", "laplacian", "density_gradient", "all"} <= set(EXTRAS)


def test_default_hashgrid_is_sized_to_the_grid():
    """The default position hash grid ends at the density grid's resolution (``max_resolution: grid``)."""
    cfg = _compose("hashgrid_oneblob", "none")
    grid = DensityGrid(torch.rand(40, 24, 20), center=(0, 0, 0), diagonal=2.0, density_scale=1.0)
    cache = build_radiance_cache(cfg.cache, cfg.encoding, cfg.extra_inputs, grid, "cpu", 0, training_paths=4608)
    enc = cache.network.encoding.encodings[0]
    assert isinstance(enc, HashGridEncoding)
    assert (enc.n_levels, enc.n_features_per_level, enc.hashmap_size) == (8, 2, 2**16)  # auto: 16 x 4,608 rows
    assert cache.log2_hashmap_size == 16
    assert enc.scales[0].item() + 1 == pytest.approx(16.0) and enc.scales[-1].item() + 1 == pytest.approx(40.0, rel=1e-5)
    assert cache.settings.n_neurons == 64 and cache.settings.n_hidden_layers == 5
    # A grid coarser than N_min puts every level at N_min.
    coarse = build_radiance_cache(cfg.cache, cfg.encoding, cfg.extra_inputs, _grid(), "cpu", 0, training_paths=4608)
    assert coarse.network.encoding.encodings[0].resolutions == (16,) * 8


@pytest.mark.parametrize(("paths", "log2"), [(1, 14), (1024, 14), (4096, 16), (4608, 16), (8192, 17),
                                             (40960, 19), (10**7, 19)])
def test_auto_hash_table_has_16_rows_per_training_path_within_2_14_to_2_19_in_thick_media(paths, log2):
    assert auto_log2_hashmap_size(paths) == log2 and auto_log2_hashmap_size(paths, thick=False) == 19
    cfg = _compose("hashgrid_oneblob", "none", ("encoding.position.n_levels=2",))
    cache = build_radiance_cache(cfg.cache, cfg.encoding, cfg.extra_inputs, _grid(), "cpu", 0, training_paths=paths)
    assert cache.network.encoding.encodings[0].hashmap_size == 2**log2


def test_auto_hash_table_needs_the_training_paths():
    cfg = _compose("hashgrid_oneblob", "none")
    with pytest.raises(ConfigError, match=r"encoding\.position\.log2_hashmap_size: 'auto' sizes the table"):
        build_radiance_cache(cfg.cache, cfg.encoding, cfg.extra_inputs, _grid(), "cpu", 0)
    with pytest.raises(ConfigError, match=r"log2_hashmap_size"):
        cfg = _compose("hashgrid_oneblob", "none", ("encoding.position.log2_hashmap_size=big",))
        build_radiance_cache(cfg.cache, cfg.encoding, cfg.extra_inputs, _grid(), "cpu", 0, training_paths=4608)


def test_spindler_hashgrid_config():
    cfg = _compose("hashgrid_spindler_oneblob", "none", ("encoding.position.log2_hashmap_size=12",))
    cache = build_radiance_cache(cfg.cache, cfg.encoding, cfg.extra_inputs, _grid(), "cpu", 0)
    enc = cache.network.encoding.encodings[0]
    assert enc.n_levels == 16 and enc.resolutions[:3] == (16, 32, 64)  # N_min 16, per-level scale 2


@pytest.mark.parametrize(
    ("encoding", "extras"),
    [(e, "none") for e in ENCODINGS] + [("hashgrid_oneblob", x) for x in EXTRAS if x != "none"],
)
def test_every_encoding_and_extras_file_builds_and_runs(encoding, extras):
    cfg = _compose(encoding, extras)
    if cfg.encoding.position.otype == "HashGrid":  # keep the test light: small tables
        cfg = _compose(encoding, extras, ("encoding.position.log2_hashmap_size=10", "encoding.position.n_levels=4"))
    from nrc.transport.lights import DirectionalLight

    grid = _grid()
    sun = DirectionalLight(torch.tensor([0.0, -1.0, 0.0]), torch.ones(3))
    cache = build_radiance_cache(cfg.cache, cfg.encoding, cfg.extra_inputs, grid, "cpu", 0, lights=(sun,))
    x = grid.box.lo + grid.box.extent * torch.rand(16, 3)
    d = torch.nn.functional.normalize(torch.randn(16, 3), dim=1)
    n_extra = {"none": 0, "density": 1, "gradient": 3, "laplacian": 1, "density_gradient": 4, "all": 5,
               "light_depth": 0}[extras]
    assert cache.inputs.extras.n_dims == n_extra
    assert (cache.inputs.light_field is not None) == (extras == "light_depth")
    assert torch.isfinite(torch.tensor(cache.train_step(x, d, torch.ones(16, 3))))
    assert cache.query(x, d).shape == (16, 3)


HASH = {"otype": "HashGrid", "n_levels": 4, "n_features_per_level": 2, "log2_hashmap_size": 10,
        "base_resolution": 4, "per_level_scale": 2.0}
CACHE = {"network": {"n_neurons": 16, "n_hidden_layers": 3}, "optimizer": {"lr": 1e-2, "eps": 1e-15},
         "ema": {"alpha": 0.99}, "loss": {"target_clamp": 100.0}}
ONEBLOB = {"otype": "OneBlob", "n_bins": 4}


@pytest.mark.parametrize(
    ("cache", "encoding", "extras", "message"),
    [
        (CACHE, {"position": {**HASH, "n_levels": 0}, "direction": ONEBLOB}, {},
         "encoding.position.n_levels must be >= 1"),
        (CACHE, {"position": {**HASH, "max_resolution": 64}, "direction": ONEBLOB}, {},
         "exactly one of per_level_scale and max_resolution"),
        (CACHE, {"position": {**HASH, "log2_hashmap_size": 30}, "direction": ONEBLOB}, {},
         "encoding.position.log2_hashmap_size must be <= 24"),
        (CACHE, {"position": {**HASH, "n_level": 4}, "direction": ONEBLOB}, {}, "unknown key(s) n_level"),
        (CACHE, {"position": {**HASH, "n_levels": 16, "per_level_scale": 4.0}, "direction": ONEBLOB}, {},
         "encoding.position.per_level_scale: the finest resolution"),
        (CACHE, {"position": HASH, "direction": HASH}, {}, "encoding.direction.otype must be one of"),
        (CACHE, {"position": {"otype": "Gaussian"}, "direction": ONEBLOB}, {}, "encoding.position.otype"),
        (CACHE, {"position": {"otype": "Frequency", "n_frequencies": 0}, "direction": ONEBLOB}, {},
         "encoding.position.n_frequencies must be >= 1"),
        (CACHE, {"position": HASH, "direction": {"otype": "OneBlob"}}, {}, "encoding.direction.n_bins is required"),
        (CACHE, {"position": HASH}, {}, "encoding.direction.otype is required"),
        (CACHE, {"position": HASH, "direction": ONEBLOB}, {"density": "yes"},
         "extra_inputs.density must be true or false"),
        (CACHE, {"position": HASH, "direction": ONEBLOB}, {"curl": True}, "extra_inputs: unknown key(s) curl"),
        ({**CACHE, "ema": {"alpha": 1.0}}, {"position": HASH, "direction": ONEBLOB}, {}, "cache.ema.alpha must be < 1"),
        ({**CACHE, "network": {"n_neurons": 64, "n_hidden_layers": 0}}, {"position": HASH, "direction": ONEBLOB}, {},
         "cache.network.n_hidden_layers must be >= 1"),
        ({**CACHE, "loss": {"target_clamp": 0.0}}, {"position": HASH, "direction": ONEBLOB}, {},
         "cache.loss.target_clamp must be > 0"),
        ({**CACHE, "loss": {"target_clamp": 1.0, "scale_floor": -0.5}}, {"position": HASH, "direction": ONEBLOB}, {},
         "cache.loss.scale_floor must be >= 0"),
        ({**CACHE, "loss": {"target_clamp": 1.0, "relative_clamp": -1}}, {"position": HASH, "direction": ONEBLOB}, {},
         "cache.loss.relative_clamp must be >= 0"),
        ({**CACHE, "loss": {"target_clamp": 1.0, "clamp_to": "median"}}, {"position": HASH, "direction": ONEBLOB}, {},
         "cache.loss.clamp_to"),
        ({**CACHE, "loss": {"target_clamp": 1.0, "clamp_excess": "keep"}}, {"position": HASH, "direction": ONEBLOB}, {},
         "cache.loss.clamp_excess"),
        ({**CACHE, "optimizer": {"lr": 1e-2}}, {"position": HASH, "direction": ONEBLOB}, {},
         "cache.optimizer.eps is required"),
        ({**CACHE, "optimizer": {**CACHE["optimizer"], "lr_final_fraction": 0.0}}, {"position": HASH, "direction": ONEBLOB},
         {}, "cache.optimizer.lr_final_fraction must be > 0"),
        ({**CACHE, "optimizer": {**CACHE["optimizer"], "lr_final_fraction": 1.5}}, {"position": HASH, "direction": ONEBLOB},
         {}, "cache.optimizer.lr_final_fraction must be <= 1"),
        ({**CACHE, "optimizer": {**CACHE["optimizer"], "lr_half_life": 0}}, {"position": HASH, "direction": ONEBLOB},
         {}, "cache.optimizer.lr_half_life must be > 0"),
        ({**CACHE, "optimizer": {**CACHE["optimizer"], "lr_hold": -1}}, {"position": HASH, "direction": ONEBLOB},
         {}, "cache.optimizer.lr_hold must be >= 0"),
        ({**CACHE, "optimizer": {**CACHE["optimizer"], "lr_final_fraction": "most"}},
         {"position": HASH, "direction": ONEBLOB}, {}, "cache.optimizer.lr_final_fraction"),
        ({**CACHE, "query_chunk": 0}, {"position": HASH, "direction": ONEBLOB}, {}, "cache.query_chunk must be >= 1"),
    ],
)
def test_bad_config_values_name_the_key(cache, encoding, extras, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        build_radiance_cache(cache, encoding, extras, _grid(), "cpu", 0)


def test_max_resolution_sets_the_per_level_scale():
    enc = {"position": {**HASH, "per_level_scale": None, "max_resolution": 32}, "direction": ONEBLOB}
    cache = build_radiance_cache(CACHE, enc, {}, _grid(), "cpu", 0)
    grid = cache.network.encoding.encodings[0]
    assert grid.scales[-1].item() + 1 == pytest.approx(32.0, rel=1e-5)  # N_max = N_min b^(L-1)
