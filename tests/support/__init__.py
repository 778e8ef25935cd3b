"""Helpers the test modules share (no tests here; test modules import these, never each other).
Shared fixtures of the whole suite stay in tests/conftest.py."""
