"""`dojo run policy=remote`: the link hands `policy.shared_memory` (auto by default) and `policy.columnar` (true by
default) to its client."""

from __future__ import annotations

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from dojo.evaluation.policy_link import open_policy
from xpolicylab.policies import load_policy
from xpolicylab.server import ServerConfig, ServerThread

REMOTE_YAML = Path(__file__).resolve().parents[2] / "dojo" / "cli" / "config" / "policy" / "remote.yaml"


@pytest.fixture(scope="module")
def url():
    with ServerThread(load_policy("zero", {"chunk_size": 2}), ServerConfig(port=0)) as srv:
        yield srv.url


def _link(cfg: dict, url: str, what: str) -> bool:
    link = open_policy({**cfg, "url": url}, "arx_x5_bimanual")
    try:
        return getattr(link.client, what)
    finally:
        link.close()


def _uses_shared_memory(cfg: dict, url: str) -> bool:
    return _link(cfg, url, "uses_shared_memory")


def test_remote_yaml_defaults_to_auto_and_a_server_on_this_host_gets_shared_memory(url):
    cfg = OmegaConf.to_container(OmegaConf.load(REMOTE_YAML))
    assert cfg["shared_memory"] == "auto"
    assert _uses_shared_memory(cfg, url)
    assert _uses_shared_memory({"name": "remote"}, url)  # a config written before the key existed


@pytest.mark.parametrize("value, used", [("off", False), (False, False), ("on", True), (True, True)])
def test_policy_shared_memory_reaches_the_client(url, value, used):
    """`policy.shared_memory=on` arrives as a string, `shared_memory: on` in a YAML file as a boolean."""
    assert _uses_shared_memory({"name": "remote", "shared_memory": value}, url) is used


def test_remote_yaml_sends_columns_and_policy_columnar_turns_them_off(url):
    cfg = OmegaConf.to_container(OmegaConf.load(REMOTE_YAML))
    assert cfg["columnar"] is True and _link(cfg, url, "sends_columns")
    assert _link({"name": "remote"}, url, "sends_columns")  # a config written before the key existed
    for value in (False, "off", "false"):
        assert not _link({"name": "remote", "columnar": value}, url, "sends_columns")
    with pytest.raises(ValueError, match="policy.columnar must be true or false"):
        _link({"name": "remote", "columnar": "sometimes"}, url, "sends_columns")
