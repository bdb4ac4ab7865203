"""`dofjax.use_compilation_cache`: where the command-line tools keep compiled programs."""

import os

import jax
import pytest

import dofjax
from dofjax import _compile_cache


@pytest.fixture
def restore_cache_dir(monkeypatch):
    before = jax.config.jax_compilation_cache_dir
    monkeypatch.delenv(_compile_cache.ENV, raising=False)
    yield
    jax.config.update("jax_compilation_cache_dir", before)


def test_explicit_directory_is_created_and_used(tmp_path, restore_cache_dir):
    d = tmp_path / "a" / "b"
    assert dofjax.use_compilation_cache(str(d)) == str(d)
    assert d.is_dir()
    assert jax.config.jax_compilation_cache_dir == str(d)


def test_empty_string_turns_it_off(tmp_path, restore_cache_dir, monkeypatch):
    jax.config.update("jax_compilation_cache_dir", str(tmp_path))
    assert dofjax.use_compilation_cache("") is None
    assert jax.config.jax_compilation_cache_dir == str(tmp_path)  # untouched
    monkeypatch.setenv(_compile_cache.ENV, "")
    assert dofjax.use_compilation_cache() is None


def test_environment_then_jax_setting_then_default(tmp_path, restore_cache_dir, monkeypatch):
    monkeypatch.setenv(_compile_cache.ENV, str(tmp_path / "env"))
    assert dofjax.use_compilation_cache() == str(tmp_path / "env")
    monkeypatch.delenv(_compile_cache.ENV)
    jax.config.update("jax_compilation_cache_dir", str(tmp_path / "jax"))
    assert dofjax.use_compilation_cache() == str(tmp_path / "jax")
    jax.config.update("jax_compilation_cache_dir", None)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert dofjax.use_compilation_cache() == os.path.join(str(tmp_path / "xdg"), "dofjax", "jax")


def test_uncreatable_directory_names_it(tmp_path, restore_cache_dir):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(OSError, match="compilation cache.*file"):
        dofjax.use_compilation_cache(str(blocker / "cache"))


def test_uncreatable_default_directory_warns_and_turns_it_off(tmp_path, restore_cache_dir,
                                                              monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    jax.config.update("jax_compilation_cache_dir", None)
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocker))  # a read-only home, say
    with pytest.warns(RuntimeWarning, match="compiling without it"):
        assert dofjax.use_compilation_cache() is None
    assert jax.config.jax_compilation_cache_dir is None


def test_cli_reports_an_uncreatable_cache_directory(tmp_path, restore_cache_dir, capsys):
    from dofjax._cli import main

    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    assert main(["--jax-cache", str(blocker / "cache"), "info", str(tmp_path / "none.exr")]) == 2
    assert "compilation cache" in capsys.readouterr().err


def test_scripts_end_with_a_message_naming_themselves(tmp_path, restore_cache_dir, capsys):
    from fit import demo

    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(SystemExit) as info:
        demo.main(["--jax-cache", str(blocker / "cache")])
    assert info.value.code == 2
    assert capsys.readouterr().err.startswith("demo: error: JAX compilation cache: cannot create")
