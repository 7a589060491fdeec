"""Shared pytest setup: CPU only, deterministic, quiet."""
import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
os.environ.setdefault("DSCPP_JAX_COMPILE_CACHE", "off")  # tests write nothing under ~/.cache
