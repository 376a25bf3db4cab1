import pytest

from cylsfm.model.config import (
    ConfigError,
    apply_overrides,
    config_from_dict,
    config_to_dict,
    load_config,
    preset,
    save_config,
)


def test_paper_presets_match_the_paper():
    s = preset("paper-synthia")
    assert (s.optim.lr, s.optim.beta1, s.batch_size, s.data.seq_length) == (2e-4, 0.9, 4, 3)
    assert (s.data.width, s.data.height, s.max_steps) == (512, 128, 60000)
    assert s.loss.smooth_weight == 2.0 and s.loss.explain_weight == 0 and s.loss.ssim_weight == 0
    h = preset("paper-headcam")
    assert h.loss.image_smooth_weight == 0.2 and h.loss.smooth_weight == 0


def test_yaml_round_trip_and_overrides(tmp_path):
    cfg = apply_overrides(
        preset("paper-synthia"), ["loss.ssim_weight=0.85", "data.width=256", "model.wrap=false"]
    )
    assert cfg.loss.ssim_weight == 0.85 and cfg.data.width == 256 and cfg.wrap is False
    save_config(cfg, tmp_path / "c.yaml")
    assert load_config(tmp_path / "c.yaml") == cfg
    assert config_from_dict(config_to_dict(cfg)) == cfg
    (tmp_path / "partial.yaml").write_text("preset: paper-headcam\nbatch_size: 8\n")
    part = load_config(tmp_path / "partial.yaml")
    assert part.batch_size == 8 and part.loss.image_smooth_weight == 0.2


def test_bad_configurations_are_clear_errors(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("loss:\n  ssim_wieght: 0.85\n")
    with pytest.raises(ConfigError, match="ssim_wieght") as info:
        load_config(bad)
    assert str(bad) in str(info.value)
    with pytest.raises(ConfigError, match="unknown key"):
        apply_overrides(preset("default"), ["loss.nope=1"])
    with pytest.raises(ConfigError, match="key=value"):
        apply_overrides(preset("default"), ["loss.ssim_weight"])
    with pytest.raises(ConfigError, match="equivariant"):
        apply_overrides(preset("improved"), ["model.pose_head=equivariant", "data.fov=90"])
    with pytest.raises(ConfigError, match="preset"):
        preset("nope")
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.yaml")


def test_rules_between_settings_are_checked_in_the_configuration():
    with pytest.raises(ConfigError, match="alternatives"):
        apply_overrides(preset("improved"), ["model.explainability=true", "loss.explain_weight=0.2"])
    with pytest.raises(ConfigError, match="no explainability"):
        apply_overrides(preset("default"), ["model.explainability=true"])
    with pytest.raises(ConfigError, match="start <= end"):
        apply_overrides(preset("default"), ["model.prior_fade_start=900"])
