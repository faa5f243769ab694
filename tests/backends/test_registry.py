"""Backends by registry: every backend is built through `make_backend` from plain options, unknown names fail
with the list of backends, and the evaluation loop gets the same backend the config names."""

from __future__ import annotations

import pytest
from dojo.backends.mujoco.backend import MujocoBackend
from dojo.backends.registry import BackendOptions, available, factory_from_config, make_backend


def test_the_installed_backends_are_listed_without_importing_them():
    assert {"mujoco", "mjx"} <= set(available())


def test_make_backend_passes_the_options_through():
    options = BackendOptions(cameras=("head",), width=64, height=48, depth=True, privileged=True,
                             plan_paths={"abc": "/plans/abc.json"}, settings={"threads": 2})
    with make_backend("mujoco", options) as backend:
        assert isinstance(backend, MujocoBackend)
        assert (backend.cameras, backend.width, backend.height, backend.depth) == (("head",), 64, 48, True)
        assert backend.privileged and backend.plan_paths == {"abc": "/plans/abc.json"} and backend.num_threads == 2


def test_plan_paths_reach_only_a_privileged_backend():
    with make_backend("mujoco", BackendOptions(plan_paths={"abc": "/plans/abc.json"})) as backend:
        assert backend.plan_paths == {}


def test_a_config_group_names_the_backend_and_carries_its_settings():
    factory = factory_from_config({"name": "mujoco", "threads": 3}, cameras=("head",))
    with factory() as backend:
        assert isinstance(backend, MujocoBackend) and backend.num_threads == 3


@pytest.mark.parametrize("name", ["mujoko", "registry"])
def test_unknown_backends_are_refused_with_the_choices(name):
    with pytest.raises(ValueError, match="mujoco"):
        make_backend(name, BackendOptions())
