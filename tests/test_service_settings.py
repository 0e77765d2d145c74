"""Service settings: defaults that run, file < environment < options, and file sources kept in their folder."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from service.errors import MeniscopeError
from service.server.settings import load_settings, resolve_source


@pytest.fixture(autouse=True)
def no_meniscope_env(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in [n for n in __import__("os").environ if n.startswith("MENISCOPE_")]:
        monkeypatch.delenv(name)


def test_defaults_bind_loopback_port_8000_run_the_demo_with_the_fast_network() -> None:
    s = load_settings()
    assert (s.host, s.port, s.source, s.method, s.zmq_publish) == (
        "127.0.0.1",
        8000,
        None,
        "network",
        "tcp://127.0.0.1:5556",
    )
    assert s.loopback and s.token is None and s.models.joinpath("manifest.json").is_file()


def test_a_config_file_is_overridden_by_the_environment_then_by_options(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = tmp_path / "serve.toml"
    config.write_text('port = 9000\nhost = "0.0.0.0"\nbatch = 64\n[fit]\nmax_modes = 1\n')
    monkeypatch.setenv("MENISCOPE_PORT", "9100")
    monkeypatch.setenv("MENISCOPE_TOKEN", "s3cret")
    s = load_settings(config, port=9200)
    assert (s.port, s.host, s.batch, s.fit.max_modes) == (9200, "0.0.0.0", 64, 1)
    assert not s.loopback and s.token is not None and s.token.get_secret_value() == "s3cret"
    assert "s3cret" not in json.dumps(s.public()) and s.public()["token_set"] is True
    assert load_settings(config).port == 9100


@pytest.mark.parametrize(
    "text, problem",
    [
        ("prot = 1\n", "unknown setting 'prot'"),
        ("port = -1\n", "port: Input should be greater than or equal to 0"),
        ('method = "fastest"\n', "method: Input should be"),
        ('method = "nearest"\n', "needs nearest_database"),
        ("port = [\n", "not a TOML or JSON config"),
    ],
)
def test_a_bad_config_is_one_line_naming_the_file_and_setting(tmp_path: Path, text: str, problem: str) -> None:
    config = tmp_path / "serve.toml"
    config.write_text(text)
    with pytest.raises(MeniscopeError, match="serve.toml") as err:
        load_settings(config)
    assert problem in str(err.value) and "\n" not in str(err.value)


def test_a_bad_value_is_named_where_it_came_from(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The environment variable or the option that set it, not a config file that did not."""
    config = tmp_path / "serve.toml"
    config.write_text("port = 9000\n")
    monkeypatch.setenv("MENISCOPE_PORT", "-5")
    with pytest.raises(MeniscopeError) as err:
        load_settings(config)
    assert str(err.value).startswith("MENISCOPE_PORT: port:") and "serve.toml" not in str(err.value)
    monkeypatch.delenv("MENISCOPE_PORT")
    with pytest.raises(MeniscopeError) as err:
        load_settings(config, port=-7)
    assert str(err.value).startswith("--port: port:")


def test_file_sources_resolve_inside_the_recordings_folder(tmp_path: Path) -> None:
    (tmp_path / "rec.cine").touch()
    assert resolve_source("rec.cine", tmp_path) == f"file://{tmp_path}/rec.cine"
    assert resolve_source(f"file://{tmp_path}/rec.cine?loop=1", tmp_path) == f"file://{tmp_path}/rec.cine?loop=1"
    assert resolve_source("zmq+tcp://10.0.0.5:5557", tmp_path) == "zmq+tcp://10.0.0.5:5557"


@pytest.mark.parametrize(
    "source",
    ["../secret.cine", "/etc/passwd", "file:///etc/passwd", "sub/../../x.cine", "file://%2E%2E/x.cine", "link.cine"],
)
def test_no_file_source_can_leave_the_recordings_folder(tmp_path: Path, source: str) -> None:
    folder = tmp_path / "recordings"
    folder.mkdir()
    (folder / "link.cine").symlink_to(tmp_path / "outside.cine")
    with pytest.raises(MeniscopeError, match="recordings folder"):
        resolve_source(source, folder)
    with pytest.raises(MeniscopeError, match="recordings folder"):
        load_settings(source=source, recordings_dir=folder)


def test_a_simulated_source_renders_the_service_scene_so_its_uri_names_no_file(tmp_path: Path) -> None:
    assert resolve_source("sim://?seed=3&noise=lab", tmp_path) == "sim://?seed=3&noise=lab"
    with pytest.raises(MeniscopeError) as err:
        load_settings(source="sim://?seed=3&scene=/etc/passwd", recordings_dir=tmp_path)
    assert "source: sim://?seed=3&scene=/etc/passwd: sim:// renders the service's scene (setting scene)" in str(
        err.value
    )
    assert "\n" not in str(err.value)


def test_settings_are_validated_once_so_an_option_mends_a_bad_value_of_the_config(tmp_path: Path) -> None:
    config = tmp_path / "serve.toml"
    config.write_text('source = "../outside.cine"\nport = 9000\n')
    (tmp_path / "recordings").mkdir()
    s = load_settings(config, recordings_dir=tmp_path / "recordings", source="rec.cine")
    assert (s.source, s.port) == ("rec.cine", 9000)
    with pytest.raises(MeniscopeError) as err:
        load_settings(config, recordings_dir=tmp_path / "recordings")
    assert str(err.value) == (
        f"{config}: source: ../outside.cine: file sources must lie in the recordings folder "
        f"{tmp_path / 'recordings'} (setting recordings_dir, MENISCOPE_RECORDINGS_DIR)"
    )


def test_fallbacks_hold_only_where_no_file_environment_or_option_sets_the_key(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = tmp_path / "serve.toml"
    config.write_text("port = 9000\n")
    fallbacks = {"port": 1234, "threads": 3, "batch": 7, "host": "0.0.0.0"}
    monkeypatch.setenv("MENISCOPE_BATCH", "64")
    s = load_settings(config, fallbacks, host="127.0.0.2")
    assert (s.port, s.threads, s.batch, s.host) == (9000, 3, 64, "127.0.0.2")


def test_a_config_written_for_the_former_activity_threshold_still_loads_with_one_warning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    config = tmp_path / "serve.toml"
    config.write_text("activity_threshold = 8.0\nejection_hz = 120\n")
    with caplog.at_level("WARNING"):
        s = load_settings(config)
    assert s.ejection_hz == 120 and s.ejection_ratio == 2.0  # the old key changes nothing
    assert [r.getMessage().count("\n") for r in caplog.records if "activity_threshold" in r.getMessage()] == [0]
    monkeypatch.setenv("MENISCOPE_ACTIVITY_THRESHOLD", "12")
    caplog.clear()
    with caplog.at_level("WARNING"):
        assert load_settings().ejection_ratio == 2.0
    assert any("activity_threshold is deprecated" in r.getMessage() for r in caplog.records)
