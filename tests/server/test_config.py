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


def test_unknown_key_lists_the_known_ones_and_values_are_checked_once_at_load():
    with pytest.raises(cfg.ConfigError) as e:
        cfg.load({"loop": {"rtae_hz": 500}})
    assert str(e.value) == ("config loop.rtae_hz: unknown key (did you mean 'rate_hz'?); "
                            "known: clock_cpu, cpu, cpu_latency_us, protocol_thread, rate_hz, realtime, spin_us")
    for bad, key, why in [
        ({"loop": {"rate_hz": 50}}, "loop.rate_hz", "must be >= 100, got 50"),
        ({"loop": {"rate_hz": float("nan")}}, "loop.rate_hz", "must be finite, got nan"),
        ({"loop": {"spin_us": "aut"}}, "loop.spin_us", "expected 'auto' or a number, got 'aut'"),
        ({"model": {"capacity": 2.5}}, "model.capacity", "expected an integer, got 2.5"),
        ({"model": {"gravity_m_per_s2": [0, 0]}}, "model.gravity_m_per_s2", "expected 3 numbers, got [0, 0]"),
        ({"model": {"gravity_m_per_s2": [0, 0, float("inf")]}}, "model.gravity_m_per_s2[2]", "must be finite, got inf"),
        ({"loop": 5}, "loop", "expected a table, got 5"),
        ({"loop": {"realtime": 1}}, "loop.realtime", "expected true or false, got 1"),
        # the transport's options, the device's and the hand's keys are refused here too
        ({"transport": {"url": "udp://127.0.0.1:9870?rcvbuf=1"}}, "transport.url",
         "unknown option 'rcvbuf' for udp transport (did you mean 'rcvbuf_bytes'?)"),
        ({"transport": {"url": "zenoh://127.0.0.1:7447/lab?ring_capacity=many"}}, "transport.url",
         "option 'ring_capacity' has a bad value 'many' (expected an integer)"),
        ({"device": {"driver": "nosuch"}}, "device.driver", "unknown device 'nosuch'"),
        ({"device": {"kind": "1dof", "inertia_kg_m2": 1e-3}}, "device.inertia_kg_m2", "does not apply to a 1dof device"),
        ({"device": {"hand": {"type": "impedance", "stiffness_n_per_m": -5}}}, "device.hand.stiffness_n_per_m",
         "must be >= 0, got -5"),
        ({"device": {"hand": {"type": "constant", "wrnech": [0, 1, 0]}}}, "device.hand.wrnech",
         "unknown key (did you mean 'wrench'?)"),
    ]:
        with pytest.raises(cfg.ConfigError) as e:
            cfg.load(bad)
        assert e.value.key == key and e.value.reason.startswith(why), (bad, str(e.value))
        assert str(e.value).startswith(f"config {key}: ")


HANDS = [
    {"type": "none"},
    {"type": "constant", "wrench": [0.0, 0.5, 0.0]},
    {"type": "sinusoid", "amplitude": [1.0, 0.0, 0.0], "frequency_hz": 2.5},
    {"type": "steps", "steps": [[0.0, [0, 0, 0]], [0.5, [0, 1, 0]]], "repeat_period_s": 1.0},
    {"type": "impedance", "target": {"type": "sinusoid", "frequency_hz": 0.5}},
    {"type": "impedance", "target": {"type": "waypoints", "points": [[0.0, [0, 0, 0]], [1.0, [0.01, 0, 0]]]}},
]


@pytest.mark.parametrize("kind, hand", [("planar", h) for h in HANDS] + [("1dof", {"type": "constant"}),
                                                                         ("spatial", {"type": "impedance"})])
def test_print_config_prints_every_key_and_loads_back_the_same(kind, hand, tmp_path):
    from hapticproxy.server.devices import hands as hd
    from hapticproxy.server.devices import sim

    s = cfg.load({"device": {"kind": kind, "hand": hand}})
    text = s.to_toml()
    for sec, keys in [("loop", cfg.LoopConfig), ("safety", cfg.SafetyConfig), ("model", cfg.ModelConfig)]:
        for k in keys.__struct_fields__:
            assert f"\n{k} = " in text.split(f"[{sec}]")[1], (sec, k)
    dev = s["device"]
    assert set(dev) == set(sim.SIM_CONFIGS[kind].__struct_fields__)     # every key of the kind, in effect
    h = dev["hand"]
    fields = set(hd.HANDS[h["type"]].__struct_fields__)
    assert set(h) == fields, (set(h) ^ fields)
    if "target" in h:
        assert set(h["target"]) == set(hd.TARGETS[h["target"]["type"]].__struct_fields__)
    assert "[device.hand]" in text and all(f"\n{k} = " in text for k in dev if k != "hand")
    f = tmp_path / "c.toml"
    f.write_text(text)
    again = cfg.load(f)
    assert again.data == s.data


def test_a_preset_on_the_command_line_wins_over_what_the_file_pins(tmp_path):
    f = tmp_path / "pinned.toml"
    f.write_text('preset = "balanced"\n[loop]\nrate_hz = 1000.0\n[model]\nepsilon_m = 0.005\ncapacity = 8\n'
                 'damping_n_s_per_m = 20.0\n')
    assert cfg.load(f).rate_hz == 1000.0 and cfg.load(f)["model"]["capacity"] == 8   # the file's keys win over its preset
    s = cfg.load(f, {"preset": "fast"})
    assert (s.rate_hz, s["model"]["capacity"], s["model"]["epsilon_m"], s["preset"]) == (512.0, 16, 0.040, "fast")
    assert s["model"]["damping_n_s_per_m"] == 20.0                   # keys the preset does not set stay
    s = cfg.load(f, {"preset": "fast", "loop": {"rate_hz": 700.0}})  # an explicit option wins over the preset
    assert s.rate_hz == 700.0 and s["model"]["capacity"] == 16
    with pytest.raises(cfg.ConfigError, match="preset"):
        cfg.load(f, {"preset": "turbo"})


def test_serve_print_config_and_preset_from_the_command_line():
    import subprocess
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "deploy" / "configs" / "udp-loopback.toml"
    out = subprocess.run([sys.executable, "-m", "hapticproxy.cli.main", "serve", "--config", str(path),
                          "--preset", "accurate", "--print-config"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    loaded = cfg.load(path, {"preset": "accurate"})
    assert out.stdout == loaded.to_toml()
    assert 'preset = "accurate"' in out.stdout and "\nrate_hz = 4000.0" in out.stdout
    assert "\n[device.hand]\ntype = " in out.stdout and "\nendstop_stiffness_n_per_m = " in out.stdout
