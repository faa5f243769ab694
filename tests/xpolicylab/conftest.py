"""Shared fixtures for the xpolicylab tests: loopback servers that are always stopped."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

from xpolicylab.embodiments import get_embodiment
from xpolicylab.model import Model
from xpolicylab.observations import synthetic_observation
from xpolicylab.policies import load_policy
from xpolicylab.server import ServerConfig, ServerThread


@contextmanager
def serving(model: Model | None = None, **config) -> Iterator[ServerThread]:
    """A server for ``model`` (default: zero policy) on a free loopback port."""
    config.setdefault("port", 0)
    config.setdefault("host", "127.0.0.1")
    with ServerThread(model or load_policy("zero", {"chunk_size": 4}), ServerConfig(**config)) as thread:
        yield thread


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def small_obs(step: int = 0, seed: int = 0) -> dict:
    """A contract-shaped observation with small images, for tests that are not about throughput."""
    return synthetic_observation(get_embodiment("arx_x5_bimanual"), width=64, height=48, step=step, seed=seed)


@pytest.fixture
def zero_server() -> Iterator[ServerThread]:
    with serving() as thread:
        yield thread
