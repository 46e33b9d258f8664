"""Config: defaults that work, presets, and bad values refused with the key and the reason."""
import pytest

from hapticproxy.server import config as cfg


def test_defaults_work_on_loopback():
    s = cfg.load()
    assert s.rate_hz == 1000.0
    assert s["transport"]["url"].startswith("udp://127.0.0.1:")
    assert s.tool_kind == "planar"


@pytest.mark.parametrize("preset", list(cfg.PRESETS))
def test_every_preset_loads_and_round_trips_through_toml(preset, tmp_path):
    s = cfg.load({"preset": preset})
    f = tmp_path / "c.toml"
    f.write_text(cfg.to_toml(s.as_dict()))
    assert cfg.load(f).data == s.data


def test_presets_trade_rate_and_capacity():
    rates = [cfg.load({"preset": p}).rate_hz for p in ("fast", "balanced", "accurate")]
    caps = [cfg.load({"preset": p})["model"]["capacity"] for p in ("fast", "balanced", "accurate")]
    assert rates == sorted(rates) and caps == sorted(caps)


def test_keys_override_the_preset():
    assert cfg.load({"preset": "fast", "loop": {"rate_hz": 700}}).rate_hz == 700.0


@pytest.mark.parametrize("bad, key", [
    ({"loop": {"rate_hz": 50}}, "loop.rate_hz"),
    ({"loop": {"rate_hz": "fast"}}, "loop.rate_hz"),
    ({"loop": {"rate_hz": float("nan")}}, "loop.rate_hz"),
    ({"loop": {"rtae_hz": 500}}, "loop.rtae_hz"),
    ({"lop": {}}, "lop"),
    ({"preset": "turbo"}, "preset"),
    ({"model": {"policy": "magic"}}, "model.policy"),
    ({"model": {"epsilon_m": -0.001}}, "model.epsilon_m"),
    ({"model": {"capacity": 0}}, "model.capacity"),
    ({"model": {"capacity": 2.5}}, "model.capacity"),
    ({"model": {"gravity_m_per_s2": [0, 0]}}, "model.gravity_m_per_s2"),
    ({"model": {"tool": "spatial"}}, "model.tool"),
    ({"controller": {"type": "pid"}}, "controller.type"),
    ({"safety": {"max_force_n": 0}}, "safety.max_force_n"),
    ({"safety": {"ramp_in_s": 0.001}}, "safety.ramp_in_s"),
    ({"safety": {"fade_s": 0.001}}, "safety.fade_s"),
    ({"transport": {"url": "tcp://127.0.0.1:1"}}, "transport.url"),
    ({"transport": {"silence_timeout_s": 0.05}}, "transport.silence_timeout_s"),
    ({"status": {"address": "localhost"}}, "status.address"),
    ({"device": {"kind": "7dof"}}, "device.kind"),
    ({"realtime": True}, "realtime"),
])
def test_bad_values_name_the_key(bad, key):
    with pytest.raises(cfg.ConfigError) as e:
        cfg.load(bad)
    assert e.value.key == key
    assert key in str(e.value)


def test_bad_toml_file(tmp_path):
    f = tmp_path / "bad.toml"
    f.write_text("[loop\nrate_hz = 1")
    with pytest.raises(cfg.ConfigError, match="not valid TOML"):
        cfg.load(f)
    with pytest.raises(cfg.ConfigError, match="no such file"):
        cfg.load(tmp_path / "missing.toml")


def test_unknown_key_suggests_the_right_one():
    with pytest.raises(cfg.ConfigError, match="did you mean 'stiffness_n_per_m'"):
        cfg.load({"controller": {"stifness_n_per_m": 1}})
