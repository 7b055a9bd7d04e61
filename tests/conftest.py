"""Shared fixtures."""

import pytest
import ray
import torch


@pytest.fixture(scope="module")
def ray_session():
    """A local Ray for the module's tests (one torch thread, two CPUs: a learner and one remote env runner)."""
    torch.set_num_threads(1)
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False, ignore_reinit_error=True)
    yield
    ray.shutdown()
