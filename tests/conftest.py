"""Shared pytest fixtures and markers."""

import importlib.util

import pytest

HAVE_BPY = importlib.util.find_spec("bpy") is not None

requires_bpy = pytest.mark.skipif(not HAVE_BPY, reason="needs the bpy module (pip install bpy==5.0.1)")
