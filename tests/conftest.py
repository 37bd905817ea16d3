"""Shared pytest fixtures (helper functions live in tests/helpers.py)."""
from __future__ import annotations

import os
import tempfile

from conceal_jax.core import parallel

# Before JAX starts: two host devices, as `python -m conceal_jax.main` gives a 2-core machine, so that the tests
# also run the concealment step with its views split over devices (never set by importing the library).
parallel.host_devices_flag(2)
# The tests' programs are small and compiled once each, so compiling is most of a cold run: without LLVM's
# optimisation passes (its expensive ones included), and with XLA's classic CPU emitters rather than its fusion
# emitters, a program compiles in a third of the time and runs a little slower, and no result changes beyond the
# tests' tolerances. A flag already in XLA_FLAGS is left as given.
TEST_XLA_FLAGS = {"--xla_backend_optimization_level": "0", "--xla_llvm_disable_expensive_passes": "true",
                  "--xla_cpu_use_fusion_emitters": "false"}
for flag, value in TEST_XLA_FLAGS.items():
  if flag not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] += f" {flag}={value}"

import gc  # noqa: E402

import jax  # noqa: E402
import pytest  # noqa: E402


@pytest.fixture
def x64():
  with jax.enable_x64(True):
    yield


@pytest.fixture(autouse=True, scope="module")
def release_compiled_programs():
  """After each test module, JAX's in-memory caches of traced and compiled programs are dropped: a worker keeps
  every program it ever compiled otherwise, and a full run grows each worker past 6 GB. A later module that
  needs one of them again loads it from the persistent cache (pytest_configure)."""
  yield
  jax.clear_caches()
  gc.collect()


def pytest_configure(config):
  """XLA's persistent compilation cache: tests that build the same program again (a resumed run, the
  same render shapes in several tests) load it instead of compiling it again. Tracing still happens, so
  the trace-count assertions keep their meaning. CONCEAL_JAX_TEST_XLA_CACHE chooses the folder."""
  del config
  folder = os.environ.get("CONCEAL_JAX_TEST_XLA_CACHE") or os.path.join(
      tempfile.gettempdir(), f"conceal_jax_xla_cache_{os.getuid()}")
  jax.config.update("jax_compilation_cache_dir", folder)
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
