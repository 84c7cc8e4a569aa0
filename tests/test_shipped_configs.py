"""The shipped configs are found by name, and the wheel carries every package and the configs."""

import json
import tomllib
from pathlib import Path

import pytest

from lerobot_sdp import shipped_configs

REPO = Path(__file__).resolve().parents[1]


def test_configs_are_found_by_name_with_or_without_suffix():
    assert shipped_configs.path("pusht_state_cpu") == REPO / "configs" / "pusht_state_cpu.json"
    assert shipped_configs.path("pusht_state_cpu.json") == shipped_configs.path("pusht_state_cpu")
    assert json.loads(shipped_configs.path("pusht_state_paper").read_text())["policy"]["type"] == "sdp"
    assert set(shipped_configs.names()) == {p.stem for p in (REPO / "configs").glob("*.json")}


def test_an_unknown_name_lists_what_is_shipped(capsys):
    with pytest.raises(SystemExit, match=r"No shipped config 'pusht'; the plugin ships \[.*'pusht_state"):
        shipped_configs.main(["pusht"])
    shipped_configs.main(["pusht_state_cpu"])
    assert capsys.readouterr().out.strip() == str(REPO / "configs" / "pusht_state_cpu.json")


def test_an_installed_package_reads_its_package_data(tmp_path, monkeypatch):
    installed = tmp_path / "site-packages" / "lerobot_sdp"
    (installed / "configs").mkdir(parents=True)
    (installed / "configs" / "mine.json").write_text("{}")
    monkeypatch.setattr(shipped_configs, "ROOTS", (installed / "configs", installed.parent / "configs"))
    assert shipped_configs.path("mine") == installed / "configs" / "mine.json"


def test_the_wheel_lists_every_package_and_ships_the_configs():
    setuptools = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    packages = {
        ".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "lerobot_sdp").rglob("__init__.py")
    }
    assert packages | {"lerobot_sdp.configs"} == set(setuptools["packages"])
    assert setuptools["package-dir"] == {"lerobot_sdp.configs": "configs"}
    assert setuptools["package-data"]["lerobot_sdp.configs"] == ["*.json"]


def test_config_path_takes_a_file_or_a_shipped_name(tmp_path):
    import argparse

    mine = tmp_path / "mine.json"
    assert shipped_configs.config_argument(str(mine)) == mine  # a file, even one not written yet
    assert shipped_configs.config_argument("pusht_state_paper") == shipped_configs.path("pusht_state_paper")
    with pytest.raises(argparse.ArgumentTypeError, match="Pass a config file or one of those names"):
        shipped_configs.config_argument("pusht_nope")
