"""Scene contract: presets compose and load; every bad value stops with one message naming the key."""

import numpy as np
import pytest
import torch

from conftest import compose
from nrc.errors import ConfigError
from nrc.scene import load_scene
from nrc.transport.lights import DirectionalLight, EnvironmentLight, PointLight

SMALL = ["scene.volume.procedural.resolution=16", "scene.camera.width=8", "scene.camera.height=6"]


@pytest.mark.parametrize(
    "preset, kinds",
    [
        ("sun", [DirectionalLight, EnvironmentLight]),
        ("sun_front", [DirectionalLight]),
        ("point", [PointLight]),
        ("sky", [EnvironmentLight]),
        ("sun_sky", [DirectionalLight, EnvironmentLight]),
    ],
)
def test_presets_load_on_the_procedural_cloud(preset, kinds):
    cfg = compose([f"scene={preset}", *SMALL])
    scene = load_scene(cfg.scene)
    assert [type(light) for light in scene.lights] == kinds
    if preset == "sun_front":  # the original `blobs` cloud on its cube lattice
        assert scene.grid.shape == (16, 16, 16)
    else:  # the cumulus, cropped to its density (+1 empty voxel a side)
        assert max(scene.grid.shape) <= 16 and min(scene.grid.shape) >= 8
    assert scene.camera.width == 8 and scene.camera.height == 6
    assert 0 < scene.grid.max_density <= 1


def test_scene_keys_follow_the_contract():
    cfg = compose(["scene=sun"])
    assert set(cfg.scene) >= {"volume", "camera", "lights", "integrator"}
    assert set(cfg.scene.volume) >= {"source", "path", "grid", "density_scale", "albedo", "g", "center", "diagonal"}
    assert set(cfg.scene.camera) == {"position", "look_at", "up", "fov_y", "width", "height"}
    assert set(cfg.scene.integrator) == {"max_scatter", "spp", "seed"}


def test_directional_light_direction_is_normalised():
    scene = load_scene(compose(["scene=sun", *SMALL, "scene.lights.0.direction=[0,-3,0]"]).scene)
    torch.testing.assert_close(scene.lights[0].direction, torch.tensor([0.0, -1.0, 0.0]))


def test_camera_frame_follows_the_contract():
    scene = load_scene(compose(SMALL + ["scene.camera.position=[0,0,10]", "scene.camera.look_at=[0,0,0]"]).scene)
    cam = scene.camera
    torch.testing.assert_close(cam.right, torch.tensor([1.0, 0.0, 0.0]))  # cross(forward=-z, up=y) = +x
    # row 0 is the top: its ray points up; column 0 points left (-x)
    o, d = cam.generate_rays(torch.tensor([0]), torch.full((1, 2), 0.5))
    assert d[0, 1] > 0 and d[0, 0] < 0


BAD = [
    ("scene.volume.density_scale=-1", "scene.volume.density_scale"),
    ("scene.volume.g=1.0", "scene.volume.g"),
    ("scene.volume.g=-1.5", "scene.volume.g"),
    ("scene.volume.albedo=1.2", "scene.volume.albedo"),
    ("scene.volume.albedo=-0.1", "scene.volume.albedo"),
    ("scene.volume.diagonal=0", "scene.volume.diagonal"),
    ("scene.camera.width=0", "scene.camera.width"),
    ("scene.camera.height=-3", "scene.camera.height"),
    ("scene.camera.fov_y=180", "scene.camera.fov_y"),
    ("scene.camera.up=[0,25,-150]", "scene.camera.up"),  # parallel to the default look_at - position
    ("scene.integrator.spp=0", "scene.integrator.spp"),
    ("scene.integrator.max_scatter=-1", "scene.integrator.max_scatter"),
    ("scene.volume.source=vdb", "scene.volume.path"),
    ("scene.volume.source=nonsense", "scene.volume.source"),
    ("++scene.volume.path=/no/such/file.vdb", None),
    ("scene.lights.0.type=spot", "scene.lights[0].type"),
    ("scene.lights.0.irradiance=[1,-1,1]", "scene.lights[0].irradiance"),
    ("scene.lights.0.direction=[0,0,0]", "scene.lights[0].direction"),
    ("scene.volume.density_scale=abc", "scene.volume.density_scale"),
    ("scene.volume.procedural.resolution=0", "scene.volume.procedural.resolution"),
]


@pytest.mark.parametrize("override, key", BAD)
def test_bad_values_name_the_key(override, key):
    overrides = SMALL + [override]
    if key is None:  # a missing VDB file
        overrides.append("scene.volume.source=vdb")
        key = "file not found"
    with pytest.raises(ConfigError, match=key.replace("[", r"\[").replace("]", r"\]")):
        load_scene(compose(overrides).scene)


def test_npz_volume_loads_with_the_right_axes(tmp_path):
    D = np.zeros((5, 4, 3), dtype=np.float32)
    D[4, 0, 0] = 1.0
    np.savez(tmp_path / "v.npz", density=D)
    cfg = compose(SMALL + ["scene.volume.source=npz", f"scene.volume.path={tmp_path / 'v.npz'}"])
    scene = load_scene(cfg.scene)
    assert scene.grid.shape == (5, 4, 3)
    corner = scene.grid.grid_to_world(torch.tensor([[4.5, 0.5, 0.5]]))
    assert float(scene.grid.lookup(corner)) == pytest.approx(1.0)


def test_npz_with_several_arrays_needs_a_key(tmp_path):
    np.savez(tmp_path / "v.npz", a=np.ones((2, 2, 2)), b=np.ones((3, 3, 3)))
    base = SMALL + ["scene.volume.source=npz", f"scene.volume.path={tmp_path / 'v.npz'}"]
    with pytest.raises(ConfigError, match="scene.volume.grid"):
        load_scene(compose(base).scene)
    assert load_scene(compose(base + ["scene.volume.grid=b"]).scene).grid.shape == (3, 3, 3)


def test_corrupt_npz_is_a_config_error(tmp_path):
    (tmp_path / "v.npz").write_bytes(b"not a zip at all")
    cfg = compose(SMALL + ["scene.volume.source=npz", f"scene.volume.path={tmp_path / 'v.npz'}"])
    with pytest.raises(ConfigError, match="scene.volume.path"):
        load_scene(cfg.scene)


@pytest.mark.parametrize("renderer", ["pt", "nrc"])
def test_a_renderer_refuses_a_scene_on_another_device(renderer):
    """``device=cuda`` with a scene built on the CPU (``load_scene(cfg.scene)`` without a device) is one error
    naming both, not a silent CPU run (needs no GPU: the check compares device types)."""
    from nrc.render.registry import make_renderer

    cfg = compose([f"renderer={renderer}", "device=cuda", "scene.volume.procedural.resolution=16",
                   "scene.camera.width=4", "scene.camera.height=4"])
    with pytest.raises(ConfigError, match="device=cuda but the scene was built on cpu"):
        make_renderer(renderer, load_scene(cfg.scene), cfg)


def test_environment_needs_radiance_or_path():
    cfg = compose(["scene=sky", *SMALL, "scene.lights.0.radiance=null"])
    with pytest.raises(ConfigError, match=r"scene.lights\[0\]"):
        load_scene(cfg.scene)


def test_latlong_environment_from_the_command_line(tmp_path):
    """The README's example: a lat-long EXR sky with `scene=sky scene.lights.0.radiance=null
    scene.lights.0.path=...`; a non-EXR file or both keys are one clear error naming the key."""
    from nrc.io import write_exr

    write_exr(tmp_path / "sky.exr", np.full((8, 16, 3), 0.5, np.float32))
    scene = load_scene(compose(["scene=sky", *SMALL, "scene.lights.0.radiance=null",
                                f"scene.lights.0.path={tmp_path / 'sky.exr'}"]).scene)
    (env,) = scene.lights
    assert env.image is not None and env.image.shape == (8, 16, 3)
    (tmp_path / "sky.png").write_bytes(b"\x89PNG\r\n\x1a\n not an exr")
    with pytest.raises(ConfigError, match=r"scene\.lights\[0\]\.path: .*not a readable EXR"):
        load_scene(compose(["scene=sky", *SMALL, "scene.lights.0.radiance=null",
                            f"scene.lights.0.path={tmp_path / 'sky.png'}"]).scene)
    with pytest.raises(ConfigError, match=r"also set scene\.lights\.0\.radiance=null"):
        load_scene(compose(["scene=sky", *SMALL, f"scene.lights.0.path={tmp_path / 'sky.exr'}"]).scene)


@pytest.mark.parametrize("preset", ["thick", "thick_cumulus"])
def test_thick_presets_load_and_render_a_few_pixels(preset, request):
    """The thick, bright presets: albedo 0.99, g 0.85, sun + sky, optical depth far above the moderate presets'
    (docs/scenes.md), and a few path-traced pixels that are finite and lit."""
    import numpy as np

    from nrc.render.registry import make_renderer
    from nrc.volume.optical_depth import scene_optical_depth

    ovs = [f"scene={preset}", "scene.camera.width=8", "scene.camera.height=5", "scene.integrator.spp=2",
           "renderer=pt", "renderer.backend=eager"]
    if preset == "thick":  # the Disney cloud (skipped without ../shared)
        ovs.append(f"scene.volume.path={request.getfixturevalue('shared_vdb')}")
    else:
        ovs.append("scene.volume.procedural.resolution=32")
    cfg = compose(ovs)
    scene = load_scene(cfg.scene)
    assert (scene.albedo, scene.g, scene.integrator.max_scatter) == (0.99, 0.85, 512)
    assert [type(light) for light in scene.lights] == [DirectionalLight, EnvironmentLight]
    assert scene_optical_depth(scene).median > 40  # the thick regime (the moderate presets: 3-17)
    image = make_renderer("pt", scene, cfg).render().image
    assert np.isfinite(image).all() and image.mean() > 0


def test_animated_scene_turns_the_camera_or_the_suns():
    """One rule for every animated run (renderer.animate): orbit turns the camera about world +y through the box
    centre, sun turns the directional lights; frame 0 and mode none leave the scene as it is."""
    from nrc.scene import animated_scene

    scene = load_scene(compose([*SMALL, "scene=sun_sky"]).scene)
    assert animated_scene(scene, "orbit", 30.0, 0) is scene and animated_scene(scene, "none", 30.0, 5) is scene
    orbit = animated_scene(scene, "orbit", 45.0, 2)  # a quarter turn
    centre = scene.grid.box.center
    rel0, rel1 = scene.camera.position - centre, orbit.camera.position - centre
    assert rel1[1].item() == pytest.approx(rel0[1].item(), abs=1e-4)
    assert (rel0[[0, 2]] * rel1[[0, 2]]).sum().item() == pytest.approx(0.0, abs=1e-3)
    assert orbit.lights == scene.lights
    sun = animated_scene(scene, "sun", 90.0, 2)  # half a turn: x and z flip
    assert sun.camera is scene.camera
    (d0,), (d1,) = scene.lights_of(DirectionalLight), sun.lights_of(DirectionalLight)
    torch.testing.assert_close(d1.direction, d0.direction * torch.tensor([-1.0, 1.0, -1.0]), atol=1e-6, rtol=0)
    assert sun.lights_of(EnvironmentLight) == scene.lights_of(EnvironmentLight)
    with pytest.raises(ConfigError, match="renderer.animate.mode"):
        animated_scene(scene, "spin", 1.0, 1)


@pytest.mark.parametrize("preset, density, g, kinds", [
    ("disney", 0.6, 0.8, [DirectionalLight]),
    ("side_lit", 0.6, 0.5, [DirectionalLight, EnvironmentLight]),
    ("back_lit_thin", 0.15, 0.95, [DirectionalLight]),
    ("point_below", 0.6, -0.3, [PointLight]),
    ("thick10", 10.0, 0.85, [DirectionalLight, EnvironmentLight]),
])
def test_scene_types_of_the_scripts_are_presets(preset, density, g, kinds, shared_vdb):
    """The scene types the benchmark scripts name (`--preset side_lit`) are files of conf/scene/ on the Disney
    cloud; the scripts' preset() is `scene=<name>`."""
    from nrc.config import PRESETS, preset as overrides

    assert preset in PRESETS and overrides(preset) == [f"scene={preset}"]
    cfg = compose([*overrides(preset), f"scene.volume.path={shared_vdb}", "scene.camera.width=8",
                   "scene.camera.height=5"])
    scene = load_scene(cfg.scene)
    assert cfg.scene.volume.source == "vdb" and float(cfg.scene.volume.density_scale) == density
    assert scene.g == pytest.approx(g) and [type(light) for light in scene.lights] == kinds
    with pytest.raises(ValueError, match="unknown scene type 'nope'"):
        overrides("nope")
