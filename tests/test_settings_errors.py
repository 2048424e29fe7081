"""A site file's mistakes are reported all at once, in one line (fixing them one run at a time took as many runs as
mistakes), an unknown key named as unknown with the field it most likely misspells, not as that field missing, and
a camera's mistakes with the camera's name (a user walkthrough of a site file with typos)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from shared.settings import MAX_ERRORS, load_settings

CAMERA = "  - {name: NE, kind: fisheye, width: 1280, height: 960}\n"


def _error(tmp_path: Path, text: str, **overrides) -> tuple[Path, str]:
    """A site file of `text` and the error loading it (with `overrides`) gives."""
    site = tmp_path / "site.yaml"
    site.write_text(text)
    with pytest.raises(ValueError) as exc:
        load_settings(site, **overrides)
    return site, str(exc.value)


def test_a_misspelt_camera_key_is_named_with_its_suggestion_not_as_the_key_missing(tmp_path):
    site, error = _error(tmp_path, "site: x\ncameras:\n  - {name: NE, kind: fisheye, width: 1280, heigth: 960}\n")
    assert error == (f"{site}: cameras.0.heigth: Extra inputs are not permitted: unknown field of camera NE "
                     "(did you mean height?)")
    assert "Field required" not in error


def test_a_misspelt_movements_key_is_named_with_its_suggestion(tmp_path):
    site, error = _error(tmp_path, "site: x\ncameras:\n" + CAMERA + "movements:\n  center: {lat_deg: 1, lon_deg: 2}\n"
                         "  legs: [{name: a, bearing_deg: 0}, {name: b, bearing_deg: 90}]\n"
                         "  inner_radius: 10\n  outer_radius_m: 40\n")
    assert error == (f"{site}: movements.inner_radius: Extra inputs are not permitted: unknown field "
                     "(did you mean inner_radius_m?)")


def test_three_mistakes_are_reported_at_once(tmp_path):
    site, error = _error(tmp_path, "site: x\nbus: {portbase: 9000}\n"
                         "cameras:\n  - {name: NE, kind: thermal, width: 1280, heigth: 960}\n")
    assert error.startswith(f"{site}: ")
    said = error.removeprefix(f"{site}: ").split("; ")
    assert sorted(said) == sorted([
        "cameras.0.kind: Input should be 'pinhole' or 'fisheye' (camera NE)",
        "cameras.0.heigth: Extra inputs are not permitted: unknown field of camera NE (did you mean height?)",
        "bus.portbase: Extra inputs are not permitted: unknown field (did you mean port_base?)"])


def test_a_missing_field_without_a_misspelling_is_still_said_missing(tmp_path):
    site, error = _error(tmp_path, "site: x\ncameras:\n  - {name: NE, kind: fisheye, width: 1280}\n")
    assert error == f"{site}: cameras.0.height: Field required (camera NE)"


def test_a_camera_without_a_name_keeps_its_index_alone(tmp_path):
    site, error = _error(tmp_path, "site: x\ncameras:\n" + CAMERA + "  - {kind: fisheye, width: 1280, height: 960}\n")
    assert error == f"{site}: cameras.1.name: Field required"


def test_an_unknown_key_with_no_close_field_gets_no_suggestion(tmp_path):
    site, error = _error(tmp_path, "site: x\ncameras:\n" + CAMERA + "detect: {colour: red}\n")
    assert error == f"{site}: detect.colour: Extra inputs are not permitted: unknown field"
    assert "did you mean" not in error


def test_a_misspelt_top_level_key_is_named_not_the_section_missing(tmp_path):
    site, error = _error(tmp_path, "site: x\ncamras:\n" + CAMERA)
    assert error == f"{site}: camras: Extra inputs are not permitted: unknown field (did you mean cameras?)"


def test_a_misspelt_key_from_set_says_it_came_from_the_command_line(tmp_path):
    site, error = _error(tmp_path, "site: x\ncameras:\n" + CAMERA, detect={"scor_thr": 0.2})
    assert error == (f"{site}: detect.scor_thr: Extra inputs are not permitted: unknown field (did you mean "
                     "score_thr?) (given on the command line: --set or a flag)")


def test_values_from_the_environment_and_the_file_are_reported_together(tmp_path, monkeypatch):
    monkeypatch.setenv("ROADSIDE_DETECT__SCORE_THR", "2")
    site, error = _error(tmp_path, "site: x\nbus: {portbase: 9000}\ncameras:\n" + CAMERA)
    assert error == (f"{site}: bus.portbase: Extra inputs are not permitted: unknown field (did you mean port_base?); "
                     "detect.score_thr: Input should be less than 1 (given by the environment: "
                     "ROADSIDE_DETECT__SCORE_THR)")


def test_a_camera_from_the_environment_is_named_and_blamed_on_it(tmp_path, monkeypatch):
    monkeypatch.setenv("ROADSIDE_CAMERAS", json.dumps([{"name": "SW", "kind": "pinhole", "width": 10, "heigth": 10}]))
    site, error = _error(tmp_path, "site: x\ncameras:\n" + CAMERA)
    assert error == (f"{site}: cameras.0.heigth: Extra inputs are not permitted: unknown field of camera SW (did you "
                     "mean height?) (given by the environment: ROADSIDE_CAMERAS)")


def test_many_mistakes_are_capped_with_a_count_of_the_rest(tmp_path):
    extra = ", ".join(f"zz{i}: 1" for i in range(MAX_ERRORS + 3))
    site, error = _error(tmp_path, "site: x\ncameras:\n" + CAMERA + f"detect: {{{extra}}}\n")
    said = error.removeprefix(f"{site}: ").split("; ")
    assert len(said) == MAX_ERRORS + 1 and said[-1] == "and 3 more"
    assert said[0] == "detect.zz0: Extra inputs are not permitted: unknown field"


def test_a_bad_camera_name_is_not_repeated_after_its_message(tmp_path):
    site, error = _error(tmp_path, "site: x\ncameras:\n  - {name: Süd, kind: pinhole, width: 10, height: 10}\n")
    assert error.startswith(f"{site}: cameras.0.name: camera name must be") and error.endswith("got 'Süd'")
