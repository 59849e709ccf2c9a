"""Shared pytest fixtures and markers."""

import importlib.util
import os

import pytest

# OpenMP threads that spin while waiting make torch 20x slower when the 2 cores are shared with
# other processes (measured: 19.6 s vs 0.88 s for one render); passive waiting costs nothing alone.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

HAVE_BPY = importlib.util.find_spec("bpy") is not None

requires_bpy = pytest.mark.skipif(not HAVE_BPY, reason="needs the bpy module (pip install bpy==5.0.1)")
