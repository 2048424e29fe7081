"""Simulator end to end: recordings, determinism, ground-truth geometry, bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

import sim.clip as clip_mod
from sim.clip import ClipConfig, simulate_clip
from sim.contact_sheet import contact_sheet
from sim.groundtruth import frame_ground_truth
from sim.recording import Recording
from sim.render import CameraRenderer, ShadowCaster, build_world, sample_environment
from sim.site import known_sites, load_site
from sim.traffic import simulate_traffic

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def clips(tmp_path_factory) -> dict[str, Path]:
    """The same small clip twice (one and two render processes) and once with another seed."""
    base = tmp_path_factory.mktemp("clips")
    common = dict(site="state_ellsworth", seconds=0.8, hz=5.0, cameras="NE,T_SW", weather="clear")
    simulate_clip(ClipConfig(out=base / "a", seed=5, workers=1, **common))
    simulate_clip(ClipConfig(out=base / "b", seed=5, workers=2, **common))
    simulate_clip(ClipConfig(out=base / "c", seed=6, workers=2, **common))
    return {k: base / k for k in "abc"}


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_same_seed_gives_byte_identical_recordings(clips):
    a, b = _files(clips["a"]), _files(clips["b"])
    assert a.keys() == b.keys()
    assert [k for k in a if a[k] != b[k]] == []


def test_another_seed_gives_other_frames(clips):
    a = Recording(clips["a"])
    c = Recording(clips["c"])
    fa = [p.read_bytes() for _, p in a.frames("NE")]
    fc = [p.read_bytes() for _, p in c.frames("NE")]
    assert fa != fc


def test_recording_round_trip(clips):
    rec = Recording(clips["a"])
    site = load_site("state_ellsworth")
    assert rec.camera_names == ["NE", "T_SW"]
    pts = np.random.default_rng(0).uniform([-40, -40, 0], [40, 40, 2], (50, 3))
    for cam in site.build_cameras():
        if cam.name in rec.cameras:
            uv_site, _ = cam.project(pts)
            uv_rec, _ = rec.cameras[cam.name].project(pts)
            np.testing.assert_allclose(uv_rec, uv_site, atol=1e-9)
    for name in rec.camera_names:
        frames = rec.frames(name)
        gt = rec.ground_truth(name)
        assert len(frames) == len(gt) == 4
        times = [t for t, _ in frames]
        assert times == sorted(times) and len(set(times)) == len(times)
        assert [g["t_ns"] for g in gt] == times
        cam = rec.cameras[name]
        img = rec.image(frames[0][1])
        assert img.shape[:2] == (cam.height, cam.width)
        assert img.ndim == (2 if cam.modality == "thermal" else 3)
        for frame in gt:
            for v in frame["vehicles"]:
                # The recorded pixel position is the camera model's projection of the recorded point.
                uv, _ = cam.project(np.array([v["xyz"]]))
                if v["uv"] is not None:
                    np.testing.assert_allclose(uv[0], v["uv"], atol=0.01)
                ll = rec.geo.to_geodetic(np.array([v["xyz"]]))[0]
                np.testing.assert_allclose(ll[:2], v["latlon"], atol=1e-8)
                assert abs(v["xyz"][2] - rec.terrain.height(v["xyz"][0], v["xyz"][1])) < 1e-3
                assert 0.0 <= v["visible_fraction"] <= 1.0
    # Cameras are not synchronised: their capture times differ.
    assert rec.frames("NE")[0][0] != rec.frames("T_SW")[0][0]
    lm = rec.landmarks("NE")
    assert 10 <= len(lm["landmarks"]) <= 30
    assert lm["noise_model"]["pixel_sigma_px"] == 2.0


def test_ground_truth_bottom_centres_land_on_the_vehicles_pixels():
    """Project each unoccluded vehicle's ground-truth bottom centre through the camera model:
    the renderer's id buffer must show that very vehicle there (for fisheye and thermal)."""
    site = load_site("state_ellsworth")
    world = build_world(site)
    env = sample_environment(np.random.default_rng(0), "clear")
    shadows = ShadowCaster(world, env)
    history = simulate_traffic(site, world.net, 3.0, seed=11, warmup_s=60)
    scene = history.state_at(1.5)
    cams = {c.name: c for c in site.build_cameras()}
    checked = 0
    for name in ("NE", "SW", "T_NE"):
        cam = cams[name]
        res = CameraRenderer(cam, world, env, shadows, seed=1).render(scene, np.random.default_rng(0))
        gt = frame_ground_truth(cam, scene, res, site.ground, site.geo)
        index = {int(i): k for k, i in enumerate(scene.ids)}
        for v in gt:
            if not v["in_image"] or v["visible_fraction"] < 0.999 or v["visible_px"] < 40:
                continue
            u, w = np.round(v["uv"]).astype(int)
            d = np.array(v["xyz"]) - cam.pose.position_m
            elevation = np.degrees(np.arctan2(-d[2], np.hypot(d[0], d[1])))
            if elevation > 25:  # steep view: the body hides the ground under it
                assert res.ids[w, u] == index[v["id"]], f"{name}: vehicle {v['id']} not at its bottom centre"
            else:  # grazing view: the ray may pass under the body, between the wheels
                window = res.ids[max(w - 3, 0) : w + 4, max(u - 3, 0) : u + 4]
                assert (window == index[v["id"]]).any(), f"{name}: vehicle {v['id']} not near its bottom centre"
            x1, y1, x2, y2 = v["box"]
            assert x1 <= v["uv"][0] <= x2 and y1 <= v["uv"][1] <= y2
            bx1, by1, bx2, by2 = v["box_visible"]
            assert bx1 >= x1 - 2 and by1 >= y1 - 2 and bx2 <= x2 + 2 and by2 <= y2 + 2
            checked += 1
        # Occlusion is real: some vehicle is partly hidden, and hidden pixels are not counted.
        assert any(0 < v["visible_fraction"] < 0.9 for v in gt), name
    assert checked >= 15


def test_intersection_site_renders(tmp_path):
    out = tmp_path / "ix"
    summary = simulate_clip(
        ClipConfig(
            site="intersection", out=out, seconds=0.5, hz=2.0, seed=1, cameras="C_NE", workers=1, weather="overcast"
        )
    )
    assert summary["frames"] == 1
    rec = Recording(out)
    gt = rec.ground_truth("C_NE")[0]
    assert sum(v["visible_px"] > 0 for v in gt["vehicles"]) >= 5
    img = rec.image(rec.path / gt["file"])
    assert img.std() > 20


def test_contact_sheet_draws_every_camera(clips, tmp_path):
    out = contact_sheet(clips["a"], tmp_path / "sheet.png", moments=2)
    img = cv2.imread(str(out))
    assert img is not None and img.shape[0] > 400 and img.shape[1] >= 2 * 480
    assert img.std() > 20


def test_contact_sheet_names_a_path_it_cannot_write(clips, tmp_path):
    with pytest.raises(ValueError, match=r"cannot write contact sheet .*sheet\.xyz"):
        contact_sheet(clips["a"], tmp_path / "sheet.xyz", moments=1)


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "roadside", *args], capture_output=True, text=True, cwd=ROOT, timeout=300
    )


def test_cli_unknown_site_is_one_clear_line(tmp_path):
    r = _cli("sim", "--site", "atlantis", "--seconds", "1", "--out", str(tmp_path / "x"))
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "unknown site 'atlantis'" in lines[0] and "state_ellsworth" in lines[0]
    assert not (tmp_path / "x").exists()


def test_cli_negative_duration_is_refused(tmp_path):
    r = _cli("sim", "--site", "state_ellsworth", "--seconds", "-3", "--out", str(tmp_path / "x"))
    assert r.returncode == 2
    assert "--seconds" in r.stderr and "must be a finite number > 0" in r.stderr
    assert not (tmp_path / "x").exists()
    r = _cli("sim", "--site", "state_ellsworth", "--seconds", "inf", "--out", str(tmp_path / "x"))
    assert r.returncode == 2 and "must be a finite number > 0, got inf" in r.stderr


@pytest.mark.parametrize("weights, message", [("bus=x", "expected TYPE=WEIGHT"),
                                              ("plane=3", "unknown vehicle type 'plane'")])
def test_cli_bad_type_weights_are_one_clear_line(tmp_path, weights, message):
    r = _cli("sim", "--site", "state_ellsworth", "--seconds", "1", "--type-weights", weights,
             "--out", str(tmp_path / "x"))
    assert r.returncode == 2
    assert message in r.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("bad", ["file_parent", "proc"])
def test_cli_unwritable_output_is_refused(tmp_path, bad):
    if bad == "file_parent":
        (tmp_path / "plain.txt").write_text("x")
        out = tmp_path / "plain.txt" / "rec"
    else:
        out = Path("/proc/roadside_rec")
    r = _cli("sim", "--site", "state_ellsworth", "--seconds", "1", "--out", str(out))
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("roadside sim: error:")
    assert not out.exists()


def test_existing_output_is_not_overwritten_without_flag(clips):
    before = _files(clips["a"])
    with pytest.raises(ValueError, match="already exists"):
        simulate_clip(ClipConfig(site="state_ellsworth", out=clips["a"], seconds=0.5, cameras="NE"))
    assert _files(clips["a"]) == before


def test_failed_run_leaves_nothing_behind(tmp_path, monkeypatch):
    calls = {"n": 0}
    real = clip_mod.frame_ground_truth

    def failing(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] > 1:
            raise RuntimeError("disk full (simulated)")
        return real(*args, **kwargs)

    monkeypatch.setattr(clip_mod, "frame_ground_truth", failing)
    out = tmp_path / "rec"
    with pytest.raises(RuntimeError, match="disk full"):
        simulate_clip(ClipConfig(site="state_ellsworth", out=out, seconds=0.6, hz=5.0, cameras="T_NE", workers=1))
    assert list(tmp_path.iterdir()) == []


def test_recording_reader_names_the_bad_file(tmp_path):
    with pytest.raises(ValueError, match=r"recording\.json is missing"):
        Recording(tmp_path)
    (tmp_path / "recording.json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        Recording(tmp_path)
    (tmp_path / "recording.json").write_text(json.dumps({"format": "roadside-recording", "version": 99}))
    with pytest.raises(ValueError, match="version 99"):
        Recording(tmp_path)


def test_bad_clip_config_values_are_named():
    for kwargs, word in [
        ({"seconds": float("nan")}, "--seconds"),
        ({"hz": 0.0}, "--hz"),
        ({"seed": -1}, "--seed"),
        ({"workers": 0}, "--workers"),
        ({"type_weights": {"bus": -2.0}}, "type weight for bus"),
        ({"demand_scale": -0.5}, "--demand-scale must be a finite number >= 0, got -0.5"),
        ({"demand_scale": float("nan")}, "--demand-scale"),
    ]:
        cfg = ClipConfig(**{"site": "state_ellsworth", "out": Path("/tmp/unused"), "seconds": 1.0, **kwargs})
        with pytest.raises(ValueError, match=word):
            cfg.validate()
    with pytest.raises(ValueError, match="unknown camera"):
        clip_mod.select_cameras(load_site("state_ellsworth"), "NE,XX")
    with pytest.raises(ValueError, match="camera NE is named twice"):
        clip_mod.select_cameras(load_site("state_ellsworth"), "NE,SW,NE")
    cfg = ClipConfig(site="state_ellsworth", out=Path("/tmp/unused"), seconds=1.0, hz=0.5)
    with pytest.raises(ValueError, match="is not one frame per camera"):
        cfg.validate()


@pytest.mark.parametrize(("change", "message"), [
    ({"camera_name": "../../escaped"}, "camera name must be 1-64 letters"),
    ({"camera_name": ""}, "camera name must be 1-64 letters"),
    ({"utc_start": "2024-06-12T19:00:00"}, "utc_start must give its time zone"),
    ({"utc_start": "noon"}, "utc_start must be an ISO date and time")])
def test_a_site_file_whose_cameras_would_write_elsewhere_or_whose_clock_is_local_is_refused(tmp_path, change,
                                                                                            message):
    import yaml

    spec = yaml.safe_load((Path(clip_mod.__file__).parent / "sites" / "intersection.yaml").read_text())
    if "camera_name" in change:
        spec["cameras"][0]["name"] = change["camera_name"]
    else:
        spec["utc_start"] = change["utc_start"]
    (tmp_path / "site.yaml").write_text(yaml.safe_dump(spec))
    with pytest.raises(ValueError, match=message):
        load_site(tmp_path / "site.yaml")


def _site_file(tmp_path: Path, change) -> Path:
    """The intersection site's file with `change` applied to its parsed YAML, written to tmp_path."""
    import yaml

    spec = yaml.safe_load((Path(clip_mod.__file__).parent / "sites" / "intersection.yaml").read_text())
    change(spec)
    (tmp_path / "site.yaml").write_text(yaml.safe_dump(spec))
    return tmp_path / "site.yaml"


@pytest.mark.parametrize(("change", "message"), [
    (lambda s: s["approaches"][0].update(bearing_deg=float("nan")),
     r"approaches\.0\.bearing_deg: Input should be a finite number"),
    (lambda s: s["cameras"][1].update(yaw_deg=float("nan")), r"cameras\.1\.yaw_deg: Input should be a finite number"),
    (lambda s: s["cameras"][0].update(pitch_deg=float("inf")), r"cameras\.0\.pitch_deg: Input should be a finite"),
    (lambda s: s.update(extent_m=400.0), r"extent_m must be at most 240 m, got 400: .*memory"),
    (lambda s: s["terrain"]["bumps"][1].update(heigth_m=s["terrain"]["bumps"][1].pop("height_m")),
     r"site\.yaml: terrain\.bumps\[1\]: unknown key 'heigth_m'"),
    (lambda s: s["terrain"].update(slopex=0.01), r"site\.yaml: terrain: unknown key 'slopex'"),
    (lambda s: s["terrain"].update(bumps=3), r"site\.yaml: terrain\.bumps must be a list"),
    (lambda s: s["terrain"]["bumps"][0].pop("sigma_m"), r"site\.yaml: terrain\.bumps\[0\]: sigma_m is missing"),
])
def test_a_site_file_with_a_bad_number_or_terrain_entry_is_refused_naming_it(tmp_path, change, message):
    path = _site_file(tmp_path, change)
    with pytest.raises(ValueError, match=message):
        load_site(path)


def test_every_site_loads_and_the_largest_extent_is_accepted(tmp_path):
    for name in known_sites():
        assert load_site(name).ground.slope_x is not None  # the terrain section reads too
    assert load_site(_site_file(tmp_path, lambda s: s.update(extent_m=240.0))).extent_m == 240.0
    # a recording simulated before the limit still reads back (its site spec, for the demo and the counts)
    from sim.site import SiteSpec

    spec = load_site(name).model_dump(mode="json")
    assert SiteSpec.model_validate({**spec, "extent_m": 300.0}).extent_m == 300.0


def _fake_recording(path: Path, marker: str) -> None:
    path.mkdir()
    (path / "recording.json").write_text(json.dumps({"format": "roadside-recording", "version": 1}))
    (path / "marker.txt").write_text(marker)


def _tree(root: Path) -> dict[str, str]:
    """Every entry under root (links not followed): file -> text, folder -> '/', link -> '-> target'."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            key = str(p.relative_to(root))
            out[key] = f"-> {os.readlink(p)}" if p.is_symlink() else "/" if p.is_dir() else p.read_text()
    return out


@pytest.mark.parametrize(("kind", "message"), [
    ("plain_folder", "replaces only a simulator recording"),
    ("other_format", "replaces only a simulator recording"),
    ("bad_json", "replaces only a simulator recording"),
    ("file", "is a file, not a folder"),
    ("link_to_recording", "is a symbolic link"),
])
def test_overwrite_refuses_anything_but_a_recording(tmp_path, kind, message):
    target = tmp_path / "out"
    if kind == "file":
        target.write_text("notes")
    elif kind == "link_to_recording":
        _fake_recording(tmp_path / "rec", "kept")
        target.symlink_to(tmp_path / "rec")
    else:
        target.mkdir()
        meta = {"plain_folder": None, "other_format": json.dumps({"format": "something-else"}), "bad_json": "{"}[kind]
        (target / ("thesis.tex" if meta is None else "recording.json")).write_text(meta or "chapter 1")
    before = _tree(tmp_path)
    with pytest.raises(ValueError, match=message):
        clip_mod._prepare_output(target, overwrite=True)
    assert _tree(tmp_path) == before


def test_overwrite_refuses_the_working_directory_and_the_folders_above_it(tmp_path, monkeypatch):
    _fake_recording(tmp_path / "rec", "kept")
    (tmp_path / "rec" / "sub").mkdir()
    before = _tree(tmp_path)
    monkeypatch.chdir(tmp_path / "rec")
    with pytest.raises(ValueError, match="is the working directory or a folder above it"):
        clip_mod._prepare_output(Path("."), overwrite=True)
    monkeypatch.chdir(tmp_path / "rec" / "sub")
    with pytest.raises(ValueError, match="is the working directory or a folder above it"):
        clip_mod._prepare_output(Path(".."), overwrite=True)
    assert _tree(tmp_path) == before


def test_overwrite_checks_come_before_the_world_is_built(tmp_path, monkeypatch):
    def no_world(site):
        raise AssertionError("the world was built")

    monkeypatch.setattr(clip_mod, "build_world", no_world)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    with pytest.raises(ValueError, match="replaces only a simulator recording"):
        simulate_clip(ClipConfig(site="state_ellsworth", out=tmp_path / "mine", seconds=0.5, overwrite=True))
    (tmp_path / "link").symlink_to(tmp_path / "elsewhere")
    with pytest.raises(ValueError, match="is a symbolic link"):
        simulate_clip(ClipConfig(site="state_ellsworth", out=tmp_path / "link", seconds=0.5))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link", "mine"]
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep me"


def test_overwrite_replaces_a_recording_and_leaves_nothing_else(tmp_path):
    _fake_recording(tmp_path / "rec", "old")
    out, tmp = clip_mod._prepare_output(tmp_path / "rec", overwrite=True)
    assert out == (tmp_path / "rec").resolve() and tmp.parent == out.parent and tmp.name.startswith(".rec.partial-")
    (tmp / "recording.json").write_text(json.dumps({"format": "roadside-recording", "version": 1}))
    (tmp / "marker.txt").write_text("new")
    clip_mod._move_into_place(tmp, out, overwrite=True)
    assert (tmp_path / "rec" / "marker.txt").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]


@pytest.mark.parametrize("overwrite", [False, True])
def test_a_folder_that_appears_during_the_run_is_left_alone(tmp_path, overwrite):
    """Another run (without --overwrite) or a person (with it) put something at --out while this run rendered."""
    out, tmp = clip_mod._prepare_output(tmp_path / "rec", overwrite=overwrite)
    (tmp / "marker.txt").write_text("this run")
    if overwrite:
        (tmp_path / "rec").mkdir()
        (tmp_path / "rec" / "notes.txt").write_text("not a recording")
    else:
        _fake_recording(tmp_path / "rec", "the other run")
    before = _tree(tmp_path)
    message = "appeared during the run" if not overwrite else "not one .* changed during the run"
    with pytest.raises(ValueError, match=f"{message}.*nothing was replaced; the new recording is at .*partial"):
        clip_mod._move_into_place(tmp, out, overwrite=overwrite)
    assert _tree(tmp_path) == before
