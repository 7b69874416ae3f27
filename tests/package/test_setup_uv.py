"""The set-up's install with uv (scripts/setup.sh): pip's settings passed on as uv's options
(scripts/uv_args.py), from text and from pip itself."""

from __future__ import annotations

import os
import subprocess
import sys

from test_gpu_scripts import SCRIPTS, load

uv_args = load("uv_args").uv_args


def test_each_setting_becomes_its_uv_option():
    config = "\n".join(
        [
            "global.index-url='https://mirror.example/simple'",
            "global.extra-index-url='file:///a/simple file:///b/simple'",
            "global.find-links='/wheels'",
            "global.constraint='/etc/c.txt'",
            "global.cert='/etc/ca.crt'",
            "global.timeout='60'",  # no source of packages: not passed on
        ]
    )
    assert uv_args(config) == [
        "--default-index",
        "https://mirror.example/simple",
        "--extra-index-url",
        "file:///a/simple",
        "--extra-index-url",
        "file:///b/simple",
        "--find-links",
        "/wheels",
        "--constraints",
        "/etc/c.txt",
        "SSL_CERT_FILE=/etc/ca.crt",
    ]
    assert uv_args("") == []
    assert uv_args(":env:.no-index='true'") == ["--no-index"]


def test_a_variable_wins_over_install_which_wins_over_global():
    config = "\n".join(
        [
            ":env:.find-links='/from-env'",  # pip config list prints :env: first
            "global.find-links='/from-global'",
            "global.index-url='https://global/simple'",
            "install.index-url='https://install/simple'",
        ]
    )
    assert uv_args(config) == ["--default-index", "https://install/simple", "--find-links", "/from-env"]


def test_from_pips_own_config_list(tmp_path):
    """What pip itself prints: a config file's values, and a PIP_* variable over the files'."""
    conf = tmp_path / "pip.conf"
    conf.write_text("[global]\nextra-index-url = file:///x/simple\n    file:///y/simple\nfind-links = /in-file\n")
    env = dict(os.environ, PIP_CONFIG_FILE=str(conf), PIP_FIND_LINKS=str(tmp_path / "from-env"))
    listed = subprocess.run(
        [sys.executable, "-m", "pip", "config", "list"], env=env, capture_output=True, text=True, check=True
    ).stdout
    out = subprocess.run(
        [sys.executable, str(SCRIPTS / "uv_args.py")], input=listed, capture_output=True, text=True, check=True
    ).stdout.splitlines()
    valued = ("--default-index", "--extra-index-url", "--find-links", "--constraints")
    pairs = [(flag, value) for flag, value in zip(out, out[1:]) if flag in valued]
    assert ("--extra-index-url", "file:///x/simple") in pairs and ("--extra-index-url", "file:///y/simple") in pairs
    assert [v for flag, v in pairs if flag == "--find-links"] == [str(tmp_path / "from-env")]
