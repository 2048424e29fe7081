"""Weight-space interpolation of a fine-tune with its starting model (training/mix.py, `roadside mix`)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch

from roadside.cli import main
from training.mix import mix_detectors
from training.model import Detector, DetectorConfig, checkpoint_loss, load_detector, save_detector

BASE = DetectorConfig(width_mult=0.25, decoder_channels=16, head_channels=8, stride=4, axis_head=True)


def _model(cfg: DetectorConfig, seed: int) -> Detector:
    torch.manual_seed(seed)
    model = Detector(cfg)
    with torch.no_grad():  # batch-norm statistics other than the initial ones, so that they are mixed visibly
        for name, buf in model.named_buffers():
            if buf.is_floating_point():
                buf.copy_(torch.rand_like(buf) + 0.5)
            elif name.endswith("num_batches_tracked"):
                buf.fill_(seed)
    return model.eval()


def test_mix_is_the_weighted_mean_of_the_shared_weights_with_the_base_architecture():
    base, tuned = _model(BASE, 1), _model(replace(BASE, vote_head=True), 2)
    b, t = base.state_dict(), tuned.state_dict()
    for weight in (0.0, 0.3, 1.0):
        mixed = mix_detectors(base, tuned, weight)
        assert mixed.config == BASE  # the vote head only the fine-tune has is left out
        m = mixed.state_dict()
        assert m.keys() == b.keys()
        for key, value in m.items():
            if value.is_floating_point():
                torch.testing.assert_close(value, (1 - weight) * b[key] + weight * t[key], rtol=0, atol=1e-6)
            else:
                assert torch.equal(value, b[key])
    assert not any("vote" in key for key in mixed.state_dict())
    x = torch.rand(1, 1, 64, 64)
    with torch.no_grad():  # at weight 1 the shared heads answer as the fine-tune's do
        got, want = mixed(x), tuned(x)
    for name in BASE.heads:
        torch.testing.assert_close(got[name], want[name])


def test_mix_refuses_a_bad_weight_or_models_of_different_architectures():
    base = _model(BASE, 1)
    for weight in (-0.1, 1.5, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="mix weight must be a number in \\[0, 1\\]"):
            mix_detectors(base, base, weight)
    with pytest.raises(ValueError, match="differ in width_mult"):
        mix_detectors(base, _model(replace(BASE, width_mult=0.5), 2), 0.5)
    with pytest.raises(ValueError, match="differ in stride"):
        mix_detectors(base, _model(replace(BASE, stride=2), 2), 0.5)
    with pytest.raises(ValueError, match="base model has the axis head, the fine-tuned one does not"):
        mix_detectors(base, _model(replace(BASE, axis_head=False), 2), 0.5)


def test_roadside_mix_writes_a_checkpoint_with_the_base_loss(tmp_path: Path, capsys):
    base_pt, tuned_pt, out = tmp_path / "base.pt", tmp_path / "tuned.pt", tmp_path / "sub" / "mixed.pt"
    save_detector(_model(BASE, 1), base_pt, loss={"heat": "focal", "beta_size": 0.1})
    save_detector(_model(replace(BASE, vote_head=True), 2), tuned_pt, loss={"heat": "focal", "beta_vote": 0.25})
    assert main(["mix", str(base_pt), str(tuned_pt), "--weight", "0.5", "--out", str(out)]) == 0
    mixed = load_detector(out)
    assert mixed.config == BASE
    assert checkpoint_loss(out) == {"heat": "focal", "beta_size": 0.1}  # the base's: the vote term has no head
    key = "heads.heat.out.weight"
    torch.testing.assert_close(mixed.state_dict()[key], 0.5 * load_detector(base_pt).state_dict()[key]
                               + 0.5 * load_detector(tuned_pt).state_dict()[key])
    assert main(["mix", str(tuned_pt), str(base_pt), "--weight", "0.5", "--out", str(out)]) == 2
    assert "the base model has the vote head, the fine-tuned one does not" in capsys.readouterr().err
    assert main(["mix", str(base_pt), str(tmp_path / "none.pt"), "--weight", "0.5", "--out", str(out)]) == 2
    assert "model file not found" in capsys.readouterr().err


def test_a_fine_tune_with_another_input_size_mixes_with_the_fine_tunes_input_size():
    """--input-long-side is a preprocessing setting (the weights keep their shapes): a fine-tune that changed it
    is still a fine-tune of its base, and the mix takes its input size."""
    base, tuned = _model(BASE, 1), _model(replace(BASE, input_long_side=1280), 2)
    mixed = mix_detectors(base, tuned, 0.5)
    assert mixed.config == replace(BASE, input_long_side=1280)
    key = "heads.heat.out.weight"
    torch.testing.assert_close(mixed.state_dict()[key], 0.5 * base.state_dict()[key] + 0.5 * tuned.state_dict()[key])


def test_roadside_mix_without_torch_says_what_to_install(tmp_path: Path, monkeypatch, capsys):
    import sys

    for name in ("training.mix", "training.model"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    monkeypatch.setitem(sys.modules, "torch", None)  # as if not installed: importing it raises ImportError
    argv = ["mix", str(tmp_path / "base.pt"), str(tmp_path / "tuned.pt"), "--weight", "0.5", "--out", str(tmp_path)]
    assert main(argv) == 2
    assert "mix needs the train extra (pip install -e '.[train]')" in capsys.readouterr().err
