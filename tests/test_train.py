"""roadside train end to end on a tiny recording: files written, steps counted, fine-tuning from a checkpoint."""

from __future__ import annotations

import json
from dataclasses import asdict, replace

import pytest

torch = pytest.importorskip("torch")

from shared.inference import input_scale  # noqa: E402
from training.model import DetectorConfig, load_detector  # noqa: E402
from training.train import TrainConfig, recording_spec, train, training_refs  # noqa: E402

TINY = DetectorConfig(width_mult=0.25, decoder_channels=16, head_channels=8, stride=4, input_long_side=320)


def test_train_writes_the_model_and_log_then_fine_tunes_from_it(small_recording, tmp_path):
    threads = torch.get_num_threads()
    try:
        first = train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "a"), steps=6, batch_size=2,
                                  crop=64, model=TINY, threads=1, log_every=2), log=lambda _m: None)
        assert first["steps"] == 6 and first["images"] == 4
        assert [json.loads(line)["step"] for line in (tmp_path / "a" / "train_log.jsonl").read_text().splitlines()] \
            == [2, 4, 6]
        assert load_detector(tmp_path / "a" / "model.pt").config == TINY

        messages = []
        second = train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "b"), steps=2, batch_size=2,
                                   crop=64, threads=1, init=str(tmp_path / "a" / "model.pt")), log=messages.append)
        # the starting model's network is kept, whatever the config says
        assert load_detector(tmp_path / "b" / "model.pt").config == TINY
        assert second["config"]["model"]["width_mult"] == TINY.width_mult
        assert any("starting from" in m for m in messages)
        # an axis head added to the starting model: the rest of the weights are kept
        train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "d"), steps=1, batch_size=2,
                          crop=64, threads=1, init=str(tmp_path / "a" / "model.pt"), add_axis_head=True),
              log=messages.append)
        start, grown = load_detector(tmp_path / "a" / "model.pt"), load_detector(tmp_path / "d" / "model.pt")
        assert grown.config.axis_head and not start.config.axis_head
        assert set(grown.state_dict()) - set(start.state_dict()) == {k for k in grown.state_dict()
                                                                     if k.startswith("heads.axis.")}
        assert "added an axis head" in " ".join(messages)
        # a vote head too (it was ignored with --init once): the axis model grows one, the rest kept
        train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "g"), steps=1, batch_size=2,
                          crop=64, threads=1, init=str(tmp_path / "d" / "model.pt"), add_axis_head=True,
                          add_vote_head=True), log=messages.append)
        voting = load_detector(tmp_path / "g" / "model.pt")
        assert voting.config == replace(grown.config, vote_head=True)
        assert set(voting.state_dict()) - set(grown.state_dict()) == {k for k in voting.state_dict()
                                                                      if k.startswith("heads.vote.")}
        assert "added a vote head" in " ".join(messages)
        # a new input size for the starting weights (the fisheye frames at full resolution)
        train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "e"), steps=1, batch_size=2,
                          crop=64, threads=1, init=str(tmp_path / "a" / "model.pt"), input_long_side=1280),
              log=messages.append)
        resized = load_detector(tmp_path / "e" / "model.pt")
        assert resized.config == replace(TINY, input_long_side=1280)
        assert "input size 320 -> 1280 px" in " ".join(messages)
        # only the offset head trained: every other weight and batch-norm statistic is the starting model's
        train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "f"), steps=3, batch_size=2,
                          crop=64, threads=1, init=str(tmp_path / "a" / "model.pt"), train_only=("offset",),
                          lr=1e-2), log=messages.append)
        before = load_detector(tmp_path / "a" / "model.pt").state_dict()
        after = load_detector(tmp_path / "f" / "model.pt").state_dict()
        changed = {k for k in before if not torch.equal(before[k], after[k])}
        assert changed and all(k.startswith("heads.offset.") for k in changed)
        assert "training only the offset head" in " ".join(messages)
        with pytest.raises(ValueError, match=r"no head \['wheels'\]"):
            train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "h"), steps=1, batch_size=2,
                              crop=64, threads=1, init=str(tmp_path / "a" / "model.pt"), train_only=("wheels",)),
                  log=lambda _m: None)
        # a head added to the starting model but left out of train_only would stay random, frozen, and be saved
        with pytest.raises(ValueError, match=r"train_only \(offset\) leaves the new vote head random and frozen"):
            train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "h"), steps=1, batch_size=2,
                              crop=64, threads=1, init=str(tmp_path / "a" / "model.pt"), add_vote_head=True,
                              train_only=("offset",)), log=lambda _m: None)
        assert not (tmp_path / "h" / "model.pt").exists()
        with pytest.raises(ValueError, match="train_only needs a trained model"):
            TrainConfig(recordings=(str(small_recording),), train_only=("offset",))
        with pytest.raises(FileNotFoundError, match=r"init model not found: .*nope\.pt"):
            train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "c"), steps=1,
                              init=str(tmp_path / "nope.pt")), log=lambda _m: None)
    finally:
        torch.set_num_threads(threads)


def test_input_scale_shrinks_but_never_enlarges():
    assert input_scale(1280, 960, 640) == 0.5
    assert input_scale(1920, 1080, 1280) == pytest.approx(2 / 3)
    assert input_scale(640, 512, 1280) == 1.0  # a thermal frame stays at its own resolution
    with pytest.raises(ValueError, match="input_long_side must be >= 32"):
        TrainConfig(recordings=("r",), out="o", input_long_side=8)


def test_a_recording_can_lend_only_some_of_its_cameras(small_recording, tmp_path):
    def cameras(*specs):
        return sorted(r.meta["camera"] for r in training_refs(TrainConfig(recordings=specs, out="o")))

    assert cameras(str(small_recording)) == ["NE", "NE", "T_SW", "T_SW"]
    assert cameras(f"{small_recording}@fisheye") == ["NE", "NE"]
    assert cameras(f"{small_recording}@thermal", f"{small_recording}@NE") == ["NE", "NE", "T_SW", "T_SW"]
    assert cameras(f"{small_recording}@pinhole") == ["T_SW", "T_SW"]
    with pytest.raises(ValueError, match=r"unknown camera\(s\) SW \(has: NE, T_SW\)"):
        cameras(f"{small_recording}@NE,SW")
    with pytest.raises(ValueError, match="no camera matches ','"):
        cameras(f"{small_recording}@,")
    with pytest.raises(ValueError, match="nothing after '@'"):
        recording_spec(f"{small_recording}@")
    # a folder with an '@' of its own is a plain path
    odd = tmp_path / "rec@2024"
    odd.mkdir()
    assert recording_spec(str(odd)) == (str(odd), None)
    assert recording_spec("a/b@visible") == ("a/b", "visible")


def test_background_workers_feed_the_training_and_a_dead_worker_stops_it(small_recording, tmp_path, monkeypatch):
    import training.train as train_module

    threads = torch.get_num_threads()
    try:
        # two processes prepare the batches; the same number of steps is trained and the log is complete
        done = train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "w"), steps=4, batch_size=2,
                                 crop=64, model=TINY, threads=1, log_every=2, workers=2), log=lambda _m: None)
        assert done["steps"] == 4 and done["workers"] == 2 and done["device"] == "cpu"
        assert [json.loads(line)["step"] for line in (tmp_path / "w" / "train_log.jsonl").read_text().splitlines()] \
            == [2, 4]
        assert load_detector(tmp_path / "w" / "model.pt").config == TINY

        # without workers a run stays reproducible from its seed: two runs, the same first loss
        a = train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "a"), steps=1, batch_size=2,
                              crop=64, model=TINY, threads=1, log_every=1), log=lambda _m: None)
        b = train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "b"), steps=1, batch_size=2,
                              crop=64, model=TINY, threads=1, log_every=1), log=lambda _m: None)
        assert a["steps"] == b["steps"] == 1
        assert (tmp_path / "a" / "train_log.jsonl").read_text().split('"s"')[0] \
            == (tmp_path / "b" / "train_log.jsonl").read_text().split('"s"')[0]

        def crash(*_args, **_kwargs):
            raise SystemExit(3)

        # a batch larger than the data is said plainly before any worker starts (it died with it there)
        with pytest.raises(ValueError, match=r"4 samples, fewer than one batch of 5: give --batch-size 4 or less"):
            train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "y"), steps=2, batch_size=5,
                              crop=64, model=TINY, threads=1, workers=1), log=lambda _m: None)

        monkeypatch.setattr(train_module, "_prepare_batches", crash)
        with pytest.raises(RuntimeError, match=r"worker died \(exit code 3\)"):
            train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "x"), steps=2, batch_size=2,
                              crop=64, model=TINY, threads=1, workers=1), log=lambda _m: None)
    finally:
        torch.set_num_threads(threads)


def test_a_file_that_is_not_a_checkpoint_is_named(tmp_path):
    (tmp_path / "model.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match=r"model\.pt: not a roadside detector checkpoint"):
        load_detector(tmp_path / "model.pt")
    torch.save({"weights": 1}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match=r"other\.pt: not a roadside detector checkpoint \(KeyError"):
        load_detector(tmp_path / "other.pt")
    with pytest.raises(ValueError, match="model file not found"):
        load_detector(tmp_path / "none.pt")


def test_a_run_that_fails_on_its_data_keeps_the_previous_log(small_recording, tmp_path):
    import cv2
    import numpy as np

    cv2.imwrite(str(tmp_path / "a.png"), np.full((64, 64), 90, np.uint8))
    (tmp_path / "ann.json").write_text(json.dumps({
        "images": [{"id": 1, "file_name": "a.png"}], "categories": [{"id": 1, "name": "car"}],
        "annotations": [{"id": 1, "image_id": 1, "category_id": 1, "bbox": [10, 10, 20, 12]}]}))
    (tmp_path / "a.png").write_bytes(b"\x89PNG cut short")  # found only when the batch is made
    out = tmp_path / "run"
    out.mkdir()
    (out / "train_log.jsonl").write_text('{"step": 50}\n')
    with pytest.raises(ValueError, match="cannot decode"):
        train(TrainConfig(coco=(str(tmp_path / "ann.json"),), out=str(out), steps=2, batch_size=1, crop=64,
                          model=TINY, threads=1), log=lambda _m: None)
    assert (out / "train_log.jsonl").read_text() == '{"step": 50}\n'


def test_train_config_names_a_bad_device_or_worker_count(tmp_path):
    with pytest.raises(ValueError, match="device must be cpu, cuda or cuda:N, got 'tpu'"):
        TrainConfig(recordings=("r",), device="tpu")
    with pytest.raises(ValueError, match="workers must be >= 0, got -1"):
        TrainConfig(recordings=("r",), workers=-1)
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match="this PyTorch has no CUDA"):
            train(TrainConfig(recordings=("r",), out=str(tmp_path / "c"), device="cuda"), log=lambda _m: None)


def test_workers_are_stopped_even_where_the_parent_catches_sigterm(small_recording, tmp_path):
    """A forked worker inherits the parent's SIGTERM handler (a service's, a test runner's): the workers must
    still stop, or the parent hangs at exit joining them (it did: pytest never returned)."""
    import multiprocessing
    import signal

    caught = []
    previous = signal.signal(signal.SIGTERM, lambda *_: caught.append(1))
    threads = torch.get_num_threads()
    try:
        train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "s"), steps=3, batch_size=2,
                          crop=64, model=TINY, threads=1, workers=2), log=lambda _m: None)
        assert multiprocessing.active_children() == []
    finally:
        signal.signal(signal.SIGTERM, previous)
        torch.set_num_threads(threads)


def test_fine_tuning_keeps_the_loss_the_checkpoint_was_trained_with(small_recording, tmp_path, capsys):
    """model.pt records its loss settings; `roadside train --init` takes them, the flags given replace them, and
    a checkpoint without them (older files) falls back to the paper's loss."""
    from roadside.cli import main
    from training.loss import LossConfig
    from training.model import checkpoint_loss, save_detector

    threads = torch.get_num_threads()
    try:
        train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "a"), steps=1, batch_size=2, crop=64,
                          model=TINY, threads=1, loss=LossConfig(heat="focal", beta_offset=0.7)), log=lambda _m: None)
        ckpt = tmp_path / "a" / "model.pt"
        assert checkpoint_loss(ckpt)["heat"] == "focal" and checkpoint_loss(ckpt)["beta_offset"] == 0.7

        def fine_tune(out: str, *flags: str) -> dict:
            argv = ["train", "--recording", str(small_recording), "--init", str(ckpt), "--out", str(tmp_path / out),
                    "--steps", "1", "--batch-size", "2", "--crop", "64", *flags]
            assert main(argv) == 0
            return json.loads((tmp_path / out / "train.json").read_text())["config"]["loss"]

        kept = fine_tune("b")
        assert kept["heat"] == "focal" and kept["beta_offset"] == 0.7 and kept["beta_size"] == 0.01
        assert "loss settings of" in capsys.readouterr().out
        assert kept["type_weights"] is None
        weighted = fine_tune("w", "--loss-type-weights", "bus=4,truck=2")
        assert weighted["type_weights"] == [1.0, 1.0, 2.0, 4.0, 1.0] and weighted["heat"] == "focal"
        assert list(checkpoint_loss(tmp_path / "w" / "model.pt")["type_weights"]) == [1.0, 1.0, 2.0, 4.0, 1.0]
        capsys.readouterr()
        assert main(["train", "--recording", str(small_recording), "--init", str(ckpt), "--out", str(tmp_path / "x"),
                     "--steps", "1", "--loss-type-weights", "lorry=2"]) != 0
        assert "unknown vehicle type(s) lorry" in capsys.readouterr().err
        def bad_weights(flag: str) -> list[str]:
            return ["train", "--recording", str(small_recording), "--init", str(ckpt), "--out", str(tmp_path / "x"),
                    "--steps", "1", "--loss-type-weights", flag]

        for flag, message in (("bus=0", "weights must be finite numbers > 0, got bus=0.0"), ("bus=nan", "got bus=nan")):
            assert main(bad_weights(flag)) != 0
            assert message in capsys.readouterr().err
        for flag, message in (("=4", "expected TYPE=WEIGHT"), ("bus=4,bus=1", "bus is given twice")):
            with pytest.raises(SystemExit):  # refused by the argument parser
                main(bad_weights(flag))
            assert message in capsys.readouterr().err
        # 'none' clears a checkpoint's type weights (which the squared heat loss could not take)
        w_ckpt, ckpt = ckpt, tmp_path / "w" / "model.pt"
        cleared = fine_tune("n", "--loss-type-weights", "none", "--heat-loss", "mse")
        assert cleared["type_weights"] is None and cleared["heat"] == "mse"
        ckpt = w_ckpt
        changed = fine_tune("c", "--heat-loss", "mse", "--beta-size", "0.2", "--no-topk", "--beta-vote", "0.5")
        assert (changed["heat"], changed["beta_size"], changed["beta_offset"], changed["topk_fraction"],
                changed["beta_vote"]) == ("mse", 0.2, 0.7, None, 0.5)
        save_detector(load_detector(ckpt), tmp_path / "old.pt")  # no loss recorded
        assert checkpoint_loss(tmp_path / "old.pt") is None
        ckpt = tmp_path / "old.pt"
        assert fine_tune("d") == json.loads(json.dumps(asdict(LossConfig())))
        (tmp_path / "bad.pt").write_bytes(b"x")
        with pytest.raises(ValueError, match=r"bad\.pt: not a roadside detector checkpoint"):
            checkpoint_loss(tmp_path / "bad.pt")
    finally:
        torch.set_num_threads(threads)


def test_an_interrupted_run_resumes_on_its_schedule(small_recording, tmp_path):
    """A run stopped after its save at step 4 resumes there with its weights and optimizer state: the learning
    rates after the resume are those of the uninterrupted schedule, the log keeps its records up to step 4 once,
    and a resume with other settings, or without a resume file, is refused with a message naming why. A fresh run
    in the same folder removes the old resume file once its model and data are ready."""
    from training.train import RESUME_FILE

    threads = torch.get_num_threads()
    base = dict(recordings=(str(small_recording),), steps=8, batch_size=2, crop=64, model=TINY, threads=1,
                log_every=1, save_every=4, seed=3)

    class Stop(Exception):
        pass

    def stop_at_step_6(msg: str) -> None:
        if msg.startswith("[train] step 6 "):
            raise Stop

    try:
        train(TrainConfig(out=str(tmp_path / "whole"), **base), log=lambda _m: None)
        out = tmp_path / "cut"
        with pytest.raises(Stop):
            train(TrainConfig(out=str(out), **base), log=stop_at_step_6)
        saved = torch.load(out / RESUME_FILE, weights_only=True)
        assert saved["step"] == 4 and saved["optimizer"]["state"]  # Adam's moments came along
        with open(out / "train_log.jsonl", "a") as f:
            f.write('{"step": 7, "lr": 0.00')  # a line torn by the kill: dropped, not an error
        msgs = []
        summary = train(TrainConfig(out=str(out), resume=True, **base), log=msgs.append)
        assert summary["steps"] == 8
        assert any("resuming" in m and "at step 4" in m for m in msgs)
        log = [json.loads(line) for line in (out / "train_log.jsonl").read_text().splitlines()]
        whole = [json.loads(line) for line in (tmp_path / "whole" / "train_log.jsonl").read_text().splitlines()]
        assert [r["step"] for r in log] == list(range(1, 9))
        assert [r["lr"] for r in log] == pytest.approx([r["lr"] for r in whole])
        def losses(records: list[dict]) -> list[dict]:
            return [{k: v for k, v in r.items() if k != "s"} for r in records]

        assert losses(log[:4]) == losses(whole[:4])  # the same seed: the same first four steps, kept as they were
        assert log[4]["s"] > log[3]["s"]  # the time already spent goes on counting
        assert load_detector(out / "model.pt").config == load_detector(tmp_path / "whole" / "model.pt").config
        final = torch.load(out / RESUME_FILE, weights_only=True)
        # Adam's own step count went on from the saved optimizer state (4 more steps on top of 4)
        assert final["step"] == 8 and all(int(st["step"]) == 8 for st in final["optimizer"]["state"].values())
        # resumed at its end, the run takes no step and writes back exactly the weights it resumed with
        train(TrainConfig(out=str(out), resume=True, **base), log=lambda _m: None)
        again = load_detector(out / "model.pt").state_dict()
        assert all(torch.equal(again[k], v) for k, v in final["model"].items())

        with pytest.raises(ValueError, match=r"resume: lr differ.*lr was 0\.002"):
            train(TrainConfig(out=str(out), resume=True, lr=1e-3, **base), log=lambda _m: None)
        with pytest.raises(ValueError, match=r"resume: seed differ.*seed was 3"):
            train(TrainConfig(out=str(out), resume=True, **{**base, "seed": 4}), log=lambda _m: None)
        # a fresh start that fails at its setup (a typo in --init) keeps the interrupted run's resume file
        with pytest.raises(FileNotFoundError, match="init model not found"):
            train(TrainConfig(out=str(out), init=str(tmp_path / "typo.pt"), overwrite=True, **base),
                  log=lambda _m: None)
        assert torch.load(out / RESUME_FILE, weights_only=True)["step"] == 8
        # a fresh run in that folder, stopped before its first save, leaves no resume file of the old run behind
        with pytest.raises(Stop):
            train(TrainConfig(out=str(out), overwrite=True, **{**base, "save_every": 100}), log=stop_at_step_6)
        with pytest.raises(FileNotFoundError, match=r"resume: no .*cut.*resume\.pt"):
            train(TrainConfig(out=str(out), resume=True, **base), log=lambda _m: None)
        with pytest.raises(FileNotFoundError, match=r"resume: no .*new.*resume\.pt"):
            train(TrainConfig(out=str(tmp_path / "new"), resume=True, **base), log=lambda _m: None)
        (tmp_path / "bad").mkdir()
        (tmp_path / "bad" / RESUME_FILE).write_bytes(b"not a checkpoint")
        with pytest.raises(ValueError, match=r"resume\.pt: not a resume file"):
            train(TrainConfig(out=str(tmp_path / "bad"), resume=True, **base), log=lambda _m: None)
    finally:
        torch.set_num_threads(threads)


def test_a_run_refuses_a_folder_holding_an_earlier_run_unless_told_to_replace_it(small_recording, tmp_path, capsys):
    """`train` into a folder with an earlier run's model.pt or resume.pt once deleted the one and overwrote the
    other without a word: it needs --resume (continue that run) or --overwrite (replace it)."""
    from roadside.cli import main
    from training.train import RESUME_FILE

    threads = torch.get_num_threads()
    cfg = TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "a"), steps=1, batch_size=2, crop=64,
                      model=TINY, threads=1)
    try:
        train(cfg, log=lambda _m: None)
        kept = (tmp_path / "a" / "model.pt").read_bytes(), (tmp_path / "a" / RESUME_FILE).read_bytes()
        with pytest.raises(ValueError, match=r"holds an earlier run's model\.pt and resume\.pt: give --resume .* or "
                                             r"--overwrite"):
            train(cfg, log=lambda _m: None)
        assert ((tmp_path / "a" / "model.pt").read_bytes(), (tmp_path / "a" / RESUME_FILE).read_bytes()) == kept
        (tmp_path / "a" / RESUME_FILE).unlink()  # a model alone is refused too
        with pytest.raises(ValueError, match=r"holds an earlier run's model\.pt: give"):
            train(cfg, log=lambda _m: None)
        assert train(replace(cfg, overwrite=True, seed=1), log=lambda _m: None)["steps"] == 1
        assert (tmp_path / "a" / "model.pt").read_bytes() != kept[0]
        # on the command line
        argv = ["train", "--recording", str(small_recording), "--init", str(tmp_path / "a" / "model.pt"), "--out",
                str(tmp_path / "a"), "--steps", "1", "--batch-size", "2", "--crop", "64"]
        assert main(argv) == 2
        assert "--overwrite to replace it" in capsys.readouterr().err
        assert main([*argv, "--overwrite"]) == 0
    finally:
        torch.set_num_threads(threads)


def test_with_steps_and_minutes_the_schedule_ends_with_the_steps(small_recording, tmp_path):
    """With both --steps and --minutes the learning rate followed the clock alone: a run that the steps ended first
    stopped at a learning rate near its peak, and the log's estimate of the steps ignored --steps. The schedule
    follows whichever is further along, and the estimate is at most the steps."""
    from training.train import WARMUP_STEPS, _lr_at

    threads = torch.get_num_threads()
    steps = WARMUP_STEPS + 1
    messages = []
    try:
        train(TrainConfig(recordings=(str(small_recording),), out=str(tmp_path / "a"), steps=steps, minutes=600,
                          batch_size=2, crop=64, model=TINY, threads=1, log_every=1), log=messages.append)
    finally:
        torch.set_num_threads(threads)
    lrs = [json.loads(line)["lr"] for line in (tmp_path / "a" / "train_log.jsonl").read_text().splitlines()]
    assert lrs[1:] == pytest.approx([_lr_at(k / steps, 2e-3) for k in range(1, steps)], rel=1e-9)
    assert max(lrs) > 0.9 * 2e-3 and lrs[-1] < 0.01 * 2e-3
    assert any(f"about {steps} steps in 600 min (the {steps} steps end the run first)" in m for m in messages)


def test_every_applies_to_coco_images_too(tmp_path):
    import cv2
    import numpy as np

    for k in range(5):
        cv2.imwrite(str(tmp_path / f"{k}.png"), np.full((48, 64), 90, np.uint8))
    (tmp_path / "ann.json").write_text(json.dumps({
        "images": [{"id": k, "file_name": f"{k}.png", "width": 64, "height": 48} for k in range(5)],
        "categories": [{"id": 1, "name": "car"}], "annotations": []}))
    refs = training_refs(TrainConfig(coco=(str(tmp_path / "ann.json"),), every=2))
    assert [r.image_path.name for r in refs] == ["0.png", "2.png", "4.png"]
