"""Blind hidden-physics harness for torchslide.diagnose (see README.md)."""
