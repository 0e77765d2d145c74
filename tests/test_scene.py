"""The scene file: validated with messages that name the field and the problem."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from service.errors import MeniscopeError
from service.scene import Scene, direction


def _example() -> dict:
    from service import DEFAULT_SCENE

    return json.loads(Path(DEFAULT_SCENE).read_text())


def test_embedded_default_is_the_shared_example(shared_dir: Path) -> None:
    shared = json.loads((shared_dir / "spec" / "scene.example.json").read_text())
    assert Scene.from_dict(shared) == Scene.from_dict(_example())


@pytest.mark.parametrize(
    ("path", "value", "expected"),
    [
        (("nozzle", "radius_mm"), -0.25, "nozzle.radius_mm"),
        (("nozzle", "outer_radius_mm"), 0.2, "outer_radius_mm (0.2) must exceed radius_mm"),
        (("camera", "fov_deg"), 120.0, "camera.fov_deg"),
        (("camera", "fov_deg"), 0.0, "camera.fov_deg"),
        (("camera", "elevation_deg"), -90.0, "camera.elevation_deg"),
        (("camera", "width_px"), 0, "camera.width_px"),
        (("camera", "roi"), [-1, 0], "camera.roi"),
        (("fluid", "reflectance"), 1.5, "fluid.reflectance"),
        (("artifacts", "ring_mm"), [0.33, 0.26], "range must be [low, high]"),
        (("artifacts", "ring_mm"), [0.1, 0.2], "must lie on the nozzle face"),
        (("light", "strength"), float("nan"), "light.strength"),
    ],
)
def test_invalid_values_are_named_in_one_line(path: tuple[str, str], value: object, expected: str) -> None:
    data = _example()
    data[path[0]][path[1]] = value
    with pytest.raises(MeniscopeError) as err:
        Scene.from_dict(data, where="bad.json")
    message = str(err.value)
    assert message.startswith("bad.json: invalid scene")
    assert expected in message
    assert "\n" not in message


def test_unknown_keys_are_rejected() -> None:
    data = _example()
    data["camera"]["zoom"] = 2
    with pytest.raises(MeniscopeError, match="camera.zoom"):
        Scene.from_dict(data)


def test_load_reports_missing_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(MeniscopeError, match="scene file not found"):
        Scene.load(tmp_path / "absent.json")
    broken = tmp_path / "broken.json"
    broken.write_text("{ nozzle: ")
    with pytest.raises(MeniscopeError, match=r"broken.json: not valid JSON"):
        Scene.load(broken)


def test_roi_must_fit_the_recording(scene: Scene) -> None:
    scene.check_roi(96, 96, "rec.cine")
    with pytest.raises(MeniscopeError, match="rec.cine: scene ROI 96x96 at \\(0, 0\\) lies outside the 64x96 frame"):
        scene.check_roi(64, 96, "rec.cine")


def test_artifacts_are_drawn_from_the_seed_on_the_ring(scene: Scene) -> None:
    spheres = scene.spheres
    assert spheres.shape == (scene.artifacts.count, 4)
    ring = np.hypot(spheres[:, 0], spheres[:, 1])
    assert np.all((ring >= 0.26) & (ring <= 0.33))
    assert np.all((spheres[:, 3] >= 0.006) & (spheres[:, 3] <= 0.018))
    assert np.all(spheres[:, 2] == 0)
    np.testing.assert_array_equal(spheres, Scene.from_dict(_example()).spheres)


def test_listed_spheres_replace_the_random_draw() -> None:
    data = _example()
    data["artifacts"]["spheres"] = [{"x": 0.3, "y": 0.0, "z": 0.0, "radius": 0.01}]
    np.testing.assert_array_equal(Scene.from_dict(data).spheres, [[0.3, 0.0, 0.0, 0.01]])


def test_hash_follows_content_not_key_order(scene: Scene) -> None:
    reordered = {k: _example()[k] for k in reversed(list(_example()))}
    assert Scene.from_dict(reordered).sha256 == scene.sha256
    changed = _example()
    changed["camera"]["exposure"] = 2.0
    assert Scene.from_dict(changed).sha256 != scene.sha256


def test_a_changed_copy_has_its_own_hash_and_spheres(scene: Scene) -> None:
    """Derived values are never carried into a copy: a changed scene must not claim the original's models."""
    assert scene.sha256 and scene.spheres.size  # read (and cached) on the original first
    mirror = scene.model_copy(update={"fluid": scene.fluid.model_copy(update={"roughness": 0.004})})
    assert mirror.sha256 == Scene.from_dict(json.loads(mirror.to_json())).sha256 != scene.sha256
    reseeded = scene.model_copy(update={"artifacts": scene.artifacts.model_copy(update={"seed": 99})})
    assert not np.array_equal(reseeded.spheres, scene.spheres)
    with pytest.raises(ValueError, match="ring_mm"):
        scene.model_copy(update={"artifacts": scene.artifacts.model_copy(update={"ring_mm": (0.0, 0.1)})})


def test_direction_follows_the_scene_convention() -> None:
    np.testing.assert_allclose(direction(0, 0), [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(direction(90, 0), [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(direction(0, -90), [0, 0, -1], atol=1e-15)


def test_older_files_keep_their_hash_and_the_new_blocks_change_it(scene: Scene) -> None:
    # the embedded scene's hash as of the first format: shipped models are tied to it
    assert scene.sha256 == "8368d3f849ae505ec6b580c5b259a2698257ae8e9f6a7709a6d2d3a8d9d9556c"
    assert "material" not in scene.as_dict()["artifacts"] and "sensor" not in scene.as_dict()
    data = _example()
    data["artifacts"]["material"] = {"roughness": 0.2, "reflectance": 0.7}
    data["sensor"] = {"offset": 0.02, "blur_sigma_px": 0.5, "full_well_e": 12000, "read_noise_e": 15}
    extended = Scene.from_dict(data)
    assert extended.sha256 != scene.sha256
    assert Scene.from_dict(json.loads(extended.to_json())) == extended
    assert extended.sphere_material.roughness == 0.2 and scene.sphere_material.roughness == scene.fluid.roughness
