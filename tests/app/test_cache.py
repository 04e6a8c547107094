"""app.files.cache: location, atomic writes, corrupt files ignored with a warning."""

import logging
import sys

import pytest

from app.files import cache


def test_env_override_and_xdg(tmp_path, monkeypatch):
    monkeypatch.setenv("TIRDEFLECT_CACHE_DIR", str(tmp_path / "c"))
    assert cache.cache_dir() == tmp_path / "c" and (tmp_path / "c").is_dir()
    monkeypatch.delenv("TIRDEFLECT_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    if sys.platform.startswith("linux"):  # macOS and Windows have their own places (platformdirs)
        assert cache.cache_dir(create=False) == tmp_path / "xdg" / "tirdeflect"


def test_settings_live_in_the_config_dir_not_the_cache(tmp_path, monkeypatch):
    """Clearing the cache must not forget the settings: they follow XDG_CONFIG_HOME on Linux."""
    monkeypatch.delenv("TIRDEFLECT_CACHE_DIR")
    monkeypatch.delenv("TIRDEFLECT_CONFIG_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg-cache"))
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg-config"))
    if sys.platform.startswith("linux"):
        assert cache.settings_path() == tmp_path / "xdg-config" / "tirdeflect" / "settings.json"
    assert cache.settings_path().parent != cache.cache_dir(create=False)
    monkeypatch.setenv("TIRDEFLECT_CONFIG_DIR", str(tmp_path / "conf"))
    assert cache.save_settings({"camera": "synthetic"}) == tmp_path / "conf" / "settings.json"
    assert cache.load_settings() == {"camera": "synthetic"}
    assert not (tmp_path / "xdg-cache").exists()


def test_wisdom_round_trip(tmp_path, monkeypatch):
    monkeypatch.setenv("TIRDEFLECT_CACHE_DIR", str(tmp_path))
    assert cache.load_wisdom() is None
    blob = bytes(range(256)) * 3
    cache.save_wisdom(blob)
    assert cache.load_wisdom() == blob
    # the write left no temporary file behind
    assert [p.name for p in tmp_path.iterdir()] == [cache.wisdom_path().name]


@pytest.mark.parametrize("damage", ["truncate", "flip", "garbage"])
def test_corrupt_wisdom_is_ignored_with_warning(tmp_path, monkeypatch, caplog, damage):
    monkeypatch.setenv("TIRDEFLECT_CACHE_DIR", str(tmp_path))
    cache.save_wisdom(b"(fftw-3.3 wisdom)" * 20)
    path = cache.wisdom_path()
    data = bytearray(path.read_bytes())
    if damage == "truncate":
        data = data[: len(data) // 2]
    elif damage == "flip":
        data[-5] ^= 0xFF
    else:
        data = bytearray(b"hello")
    path.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING, logger="app.files.cache"):
        assert cache.load_wisdom() is None
        assert cache.restore_fftw_wisdom() is False
    assert "FFTW wisdom" in caplog.text and "ignoring" in caplog.text


def test_settings_round_trip_and_corrupt(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv("TIRDEFLECT_CONFIG_DIR", str(tmp_path))
    assert cache.load_settings() == {}
    cache.save_settings({"camera": "synthetic", "exposure_us": 500})
    assert cache.load_settings() == {"camera": "synthetic", "exposure_us": 500}
    cache.settings_path().write_text("{not json")
    with caplog.at_level(logging.WARNING, logger="app.files.cache"):
        assert cache.load_settings() == {}
    assert "corrupt" in caplog.text
