"""Shared fixtures: the initialised backend, and JIT clean-up between test modules."""

from __future__ import annotations

import pytest

from ngp_mi import backend


@pytest.fixture(scope="session")
def mi():
    """The ``mitsuba`` module with the project's variant set."""
    return backend.mitsuba()


@pytest.fixture(scope="module", autouse=True)
def _release_jit_memory():
    yield
    backend.jit_cleanup()
